"""Stage `trajectory`: centreline graph + SDF -> one camera path per sequence.

Sequence ``i`` of the configured ``sequences`` list follows the ``i``-th target
of ``trajectory.targets`` (see :func:`room_pipeline.planning.trajectory.select_targets`).
Writes ``<patient>/sequence_YYY/metadata/{trajectory.json, timestamps.json, trajectory_tum.txt}``.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

from omegaconf import DictConfig

from ..anatomy.centreline import CentrelineGraph
from ..catalog import split_key
from ..config.compose import patient_entry, section
from ..errors import ConfigError
from ..io.atomic import write_json, write_text
from ..io.volume import read_nifti_sdf
from ..planning.trajectory import (TrajectoryParams, plan_path, read_start_pose, select_targets, start_point,
                                   timestamps_dict, volume_sdf_fn)
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    s = patient_paths(cfg, patient).seq(sequence)
    return [s.trajectory, s.timestamps, s.trajectory_tum]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    sequences = list(cfg.get("sequences") or [])
    if sequence not in sequences:
        raise ConfigError(f"unknown sequence '{sequence}' (sequences: {', '.join(sequences) or 'none'})")
    params = TrajectoryParams.from_dict(section(cfg, "trajectory"))
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        graph = CentrelineGraph.from_dict(read_json(paths.centreline_graph))
        sdf = read_nifti_sdf(paths.sdf)
        # optional user start pose of the patient entry (conf/patients/*: start_pose: a Med-MPD start*.txt, 4x4, mm);
        # leaf targets are then drawn from the branches below it
        start_file = patient_entry(cfg, patient).get("start_pose")
        start = read_start_pose(start_file) if start_file else None
        below = start_point(graph, start, params)[0] if start is not None else None
        targets = select_targets(graph, params, below=below)
        index = sequences.index(sequence)
        if index >= len(targets):
            raise ConfigError(f"{sequence} needs target #{index + 1} but trajectory.targets='{params.targets}' "
                              f"yields {len(targets)} for {patient}")
        traj = plan_path(graph, targets[index], volume_sdf_fn(sdf), params, start=start)
    if start_file:  # DVC tracks the entry (params patients.<id>); the bytes it read are recorded here
        traj.start.update(file=str(start_file), sha256=hashlib.sha256(Path(start_file).read_bytes()).hexdigest())
    out = paths.seq(sequence)
    doc = traj.to_dict()
    doc["metadata"] = metadata("trajectory", patient, cfg, ("trajectory",), sequence=sequence,
                               target_index=index)
    write_json(out.trajectory, doc)
    write_json(out.timestamps, timestamps_dict(traj))
    write_text(out.trajectory_tum, traj.to_tum())
    summary = traj.summary()
    metrics = {"frames": summary["frames"], "duration_s": round(summary["duration_s"], 3),
               "length_mm": round(summary["length_m"] * 1e3, 3),
               "max_curvature_per_m": round(summary["max_curvature_per_m"], 3),
               "kappa_max_per_m": round(summary["kappa_max_per_m"], 3),
               "min_clearance_mm": round(summary["min_clearance_m"] * 1e3, 4),
               "min_clearance_minus_margin_mm": round(summary["min_clearance_minus_margin_m"] * 1e3, 4),
               "target_reached": bool(traj.target.reached),
               "target_stop_distance_mm": round(traj.target.stop_distance * 1e3, 3),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "trajectory", metrics, sequence=sequence)
    return metrics
