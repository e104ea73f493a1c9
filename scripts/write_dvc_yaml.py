#!/usr/bin/env python3
"""Regenerate dvc.yaml from the stages' own output declarations, the catalogue's paths and the stages' code deps.

Run after adding a stage or changing a stage's imports, outputs or inputs:
``python scripts/write_dvc_yaml.py``.  ``tests/test_spine.py`` fails when dvc.yaml is stale.

No file or folder name of the dataset is spelled here (``tests/test_spine.py`` checks it): every path is built by
:mod:`room_pipeline.paths` / :mod:`room_pipeline.catalog` on DVC placeholders (``PatientPaths("${output_dir}",
"${key}")`` gives ``${output_dir}/${key}/...``), so a name lives only in the catalogue.

- **outs, metrics, plots**: what ``room stage NAME`` itself declares and cleans before it runs
  (:func:`room_pipeline.cli.stage_output_paths`: the stage module's ``outputs()``, its metrics file and the
  timing file beside it), called with placeholder keys.  The metrics file is a DVC metric, the timing file an
  uncached out (``dvc exp show`` compares accuracy only), the per-frame error CSVs are DVC plots.
- **file deps**: :data:`DEPS` below, each a catalogue path on placeholders; plus the stage's code
  (``scripts/stage_deps.py``).
- **fan-out**: :data:`room_pipeline.stages.FAN_OUT` (``foreach`` over ``${phantoms}`` / ``${patients}``, a
  ``matrix`` over patients x ``${sequences}``, once for the dataset, once for the depth CNN's training patient).
- **train_depth and ``sequences``**: train_depth trains on every configured sequence of its patient, and a
  dvc.yaml dep cannot be interpolated from a list (DVC: "Cannot interpolate data of type 'list'").  Copying
  the default ``sequences`` into this file went stale after ``dvc exp run -S 'sequences=[...]'``: the new
  sequences' frames were no deps, so DVC ran train_depth without waiting for their render/noise stages and
  without seeing their frames change.  Instead train_depth depends on the training patient's
  :attr:`PatientPaths.sequence_index` folder (``<patient>/sequence_index/``), where every sequence's `render`
  and `noise` stage writes one record (``<sequence>.render.json``, ``<sequence>.noise.json``: the sha256 of
  the frames, calibration and render.json train_depth reads; :func:`stages.common.write_sequence_record`).  A
  dep on a folder that other stages' outs lie in makes DVC run train_depth after each of those stages, for
  whatever ``sequences`` is when DVC reads dvc.yaml, and the folder's hash changes when a sequence is added or
  its frames change.  ``sequences`` stays a param of train_depth (it decides which sequences it reads, and a
  removed sequence's record stays on disk).  The patient folder itself cannot be the dep: it holds
  train_depth's own outs (a cycle for DVC).  Cost: each render/noise run hashes the frames it wrote once more.
  As for the tables' ``evaluation/`` dep, the ``.gitignore`` DVC writes into the folder counts in its hash (a
  failed ``dvc exp run`` that drops it makes train_depth look changed once).
"""
from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_deps import ROOT, package_deps  # noqa: E402

sys.path.insert(0, str(ROOT / "src"))
from room_pipeline import catalog, stages  # noqa: E402
from room_pipeline.cli import stage_output_paths  # noqa: E402
from room_pipeline.io.metrics import is_timing_file, timing_path  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402

OUT = "${output_dir}"
#: the depth CNN's training patient (train_depth runs once, for it)
TRAIN = "${depth.cnn.checkpoint_patient}"
#: the DVC placeholder of the `room stage --patient` key of each fan-out
KEY = {"phantoms": "${key}", "patients": "${key}", "sequences": "${item.patient}/${item.sequence}",
       "training": TRAIN, "dataset": "all"}

K = PatientPaths(Path(OUT), "${key}")                 # a foreach stage's patient
Q = PatientPaths(Path(OUT), "${item.patient}")        # a matrix stage's patient ...
S = Q.seq("${item.sequence}")                          # ... and its sequence
T = PatientPaths(Path(OUT), TRAIN)
#: the image folder the depth stages read (depth.input: one of catalog.RGB_SOURCES)
DEPTH_INPUT = "${depth.input}"

#: name -> file deps (upstream outputs and input files; the code deps are added from the import closure)
DEPS = {
    "phantom": [],
    "segment": ["${item.input}"],
    "sdf": [K.airway_mask],
    "mesh": [K.sdf],
    "validate_anatomy": [K.ground_truth, K.airway_mask, K.sdf, K.mesh],
    "medial_axis": [K.sdf],
    "validate_centreline": [K.ground_truth, K.centreline_graph],
    # the patient entry (params) holds its optional start_pose file (a DVC matrix cannot declare a per-item
    # optional file dep, iterative/dvc#10094; trajectory.json records the file's sha256)
    "trajectory": [Q.centreline_graph, Q.sdf],
    "simulate": [S.trajectory, Q.collision_mesh, Q.mesh_metadata, Q.centreline_graph],
    # reads the planned or the simulated poses (render.poses), so both are listed
    "render": [S.trajectory, S.simulation, Q.mesh, Q.centreline_graph],
    # the profile and its folder (the profile's .json sits next to it; not dataset files)
    "noise": [S.folder("rgb"), "${noise.profile}", "data/noise_profiles"],
    # reads rgb_noisy (evaluate.pose.images: noisy) or rgb
    "evaluate_pose": [S.folder("rgb"), S.rgb_noisy, S.calibration, S.render_json, Q.centreline_graph],
    # every configured sequence of the training patient, through the records of its render and noise stages
    # (module docstring)
    "train_depth": [T.sequence_index],
    "evaluate_depth": [S.root / DEPTH_INPUT, S.folder("depth"), S.calibration, S.render_json, T.depth_model],
    # once over the dataset: every evaluation result lives under ${output_dir}/evaluation
    "tables": [catalog.evaluation_root(OUT)],
}

#: name -> params
PARAMS = {
    "phantom": ["phantom", "phantoms.${key}"], "segment": ["segment", "patients.${key}"], "sdf": ["sdf"],
    "mesh": ["mesh"], "validate_anatomy": ["sdf", "mesh"], "medial_axis": ["medial_axis"],
    "validate_centreline": ["medial_axis"], "trajectory": ["trajectory", "sequences", "patients.${item.patient}"],
    "simulate": ["simulate"], "render": ["render"], "noise": ["noise"], "evaluate_pose": ["evaluate.pose"],
    "train_depth": ["depth.train", "depth.cnn", "depth.valid_range_mm", "depth.input", "sequences"],
    "evaluate_depth": ["depth"],
    "tables": ["evaluate.tables", "evaluate.pose.methods", "depth.cnn.checkpoint_patient",
               "depth.train.eval_patients"],
}

#: the config the stages' output declarations are evaluated on: every path they read from it is a placeholder
TEMPLATE_CFG = OmegaConf.create({"output_dir": "\\" + OUT,
                                 "evaluate": {"tables": {"output_dir": "\\${evaluate.tables.output_dir}"}}})

HEADER = """\
# Generated by scripts/write_dvc_yaml.py from the stages' output declarations and the catalogue's paths
# (edit the stage modules / room_pipeline.paths / DEPS there, then rerun it).
# One stage per pipeline step; each lists its code (the sub-packages of `room stage NAME`'s import
# closure as folders, top-level and stage modules as files), its upstream outputs, the params it reads
# and its outs.
# Patients fan out with foreach over `phantoms` / `patients` in params.yaml.
"""


def stage_files(name: str) -> tuple[list[str], list[str], list[str], str]:
    """(outs, timing outs, plots, metrics file) of stage ``name``, as dvc.yaml placeholders."""
    fan = stages.FAN_OUT[name]
    paths = [str(p) for p in stage_output_paths(TEMPLATE_CFG, name, KEY[fan])]
    metrics = [p for p in paths if str(timing_path(p)) in paths]
    assert len(metrics) == 1, (name, paths)
    timing = [p for p in paths if is_timing_file(p)]
    plots = [p for p in paths if Path(p).name in catalog.PER_FRAME_CSVS]
    outs = [p for p in paths if p not in metrics + timing + plots]
    return outs, timing, plots, metrics[0]


def render() -> str:
    lines = [HEADER.rstrip("\n"), "stages:"]
    for name in stages.STAGES:
        fan = stages.FAN_OUT[name]
        cmd = f"room stage {name} --patient {KEY[fan]} --params params.yaml --quiet"
        if fan in ("dataset", "training"):
            ind = "    "
            lines += [f"  {name}:", f"{ind}cmd: {cmd}"]
        elif fan == "sequences":
            ind = "    "
            lines += [f"  {name}:", "    matrix:", "      patient: ${patients}", "      sequence: ${sequences}",
                      f"{ind}cmd: {cmd}"]
        else:
            ind = "      "
            lines += [f"  {name}:", f"    foreach: ${{{fan}}}", "    do:", f"{ind}cmd: {cmd}"]
        outs, timing, plots, metrics = stage_files(name)
        lines += [f"{ind}deps:"] + [f"{ind}  - {d}" for d in [str(d) for d in DEPS[name]] + package_deps(name)]
        lines += [f"{ind}params:"] + [f"{ind}  - {p}" for p in PARAMS[name]]
        lines += [f"{ind}outs:"]
        for o in outs:   # the dataset-level report tables belong in git, not the DVC cache
            lines += [f"{ind}  - {o}:", f"{ind}      cache: false"] if fan == "dataset" else [f"{ind}  - {o}"]
        for o in timing:
            lines += [f"{ind}  - {o}:", f"{ind}      cache: false"]
        if plots:
            lines += [f"{ind}plots:"] + [x for o in plots for x in (f"{ind}  - {o}:", f"{ind}      x: frame",
                                                                      f"{ind}      cache: false")]
        lines += [f"{ind}metrics:", f"{ind}  - {metrics}:", f"{ind}      cache: false"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    (ROOT / "dvc.yaml").write_text(render(), encoding="utf-8")
    print("wrote dvc.yaml")
