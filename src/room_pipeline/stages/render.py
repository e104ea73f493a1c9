"""Stage `render`: a sequence's camera poses + the lumen mesh -> the ROOM modalities.

Load the poses (planned or simulated), the mesh and the centreline graph; render the frames
(:func:`room_pipeline.render.sequence.render_sequence`: the folders, formats and the fan-out over the
``execution`` workers are described there); save ``segmentation/legend.json``,
``point_clouds/point_clouds.json``, ``calibration/camera_params.json``, ``metadata/render.json`` and the
metrics (with the realism statistics of the clean RGB, :mod:`room_pipeline.realism`).
"""
from __future__ import annotations

from omegaconf import DictConfig

from ..anatomy.centreline import CentrelineGraph
from ..catalog import split_key
from ..config.compose import section
from ..execution import ensure_writable, remove_stale_temp_files
from ..io.atomic import write_json
from ..io.mesh import read_obj
from ..render.params import RenderParams
from ..render.sequence import execution_params, load_poses, render_sequence, select_frames
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics, write_sequence_record


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    seq = patient_paths(cfg, patient).seq(sequence)
    return seq.render_folders() + [seq.calibration, seq.render_json,
                                   patient_paths(cfg, patient).sequence_record(sequence, "render")]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = RenderParams.from_dict(section(cfg, "render"))
    execution_params(cfg)                                   # bad execution config: stop before any work
    paths = patient_paths(cfg, patient)
    sp = paths.seq(sequence)
    with StageTimer() as timer:
        ts, poses = load_poses(sp.metadata, p.poses)
        src = select_frames(len(ts), p, sequence)
        ex_params = execution_params(cfg, len(src))
        ensure_writable(*sp.render_folders(), sp.calibration, sp.metadata)
        remove_stale_temp_files(sp.root)
        mesh = read_obj(paths.mesh)
        graph = CentrelineGraph.from_dict(read_json(paths.centreline_graph))
        out = render_sequence(p, mesh, graph, ts, poses, src, sp.root, ex_params, key)
    docs = out.documents(metadata("render", patient, cfg, ("render",), sequence=sequence))
    if "legend" in docs:
        write_json(sp.legend, docs["legend"])
    write_json(sp.point_cloud_json, docs["point_clouds"])
    write_json(sp.camera, docs["camera"])
    write_json(sp.render_json, docs["render"])
    metrics = out.metrics(timer.wall_s)
    metrics["cpu_time_s"] = round(timer.cpu_s, 3)        # driver + its workers, every modality and the meter
    metrics["cpu_seconds_per_frame"] = round(timer.cpu_s / max(1, metrics["frames"]), 4)
    if "rgb" in p.modalities:   # realism metrics of the clean RGB (room_pipeline.realism; real-frame distances: room realism)
        from ..realism import sequence_metrics

        metrics.update(sequence_metrics(sorted(sp.folder("rgb").glob("frame_*.png"))))
        if out.frame_ev is not None:
            metrics["exposure_ev_min"], metrics["exposure_ev_max"] = min(out.frame_ev), max(out.frame_ev)
    # what train_depth reads of this sequence (its DVC dep: scripts/write_dvc_yaml.py)
    write_sequence_record(paths, sequence, "render", {m: sp.folder(m) for m in ("rgb", "depth")}
                          | {"calibration": sp.calibration, "render_json": sp.render_json})
    write_metrics(paths, "render", metrics, sequence=sequence)
    return metrics
