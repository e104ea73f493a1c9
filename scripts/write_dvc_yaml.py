#!/usr/bin/env python3
"""Regenerate dvc.yaml from the stage table below and the stages' exact code deps.

Run after adding a stage or changing a stage's imports:
``python scripts/write_dvc_yaml.py``.  ``tests/test_spine.py`` fails when
dvc.yaml and this table (or the import closure) disagree.
"""
from __future__ import annotations

import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_deps import ROOT, package_deps  # noqa: E402

P = "${output_dir}/${key}"
#: per-sequence stages fan out over patients x sequences (DVC matrix; a dict matrix yields its keys)
MATRIX = "matrix"
#: once for the whole dataset (`room stage NAME --patient all`)
DATASET = "dataset"
#: once for the depth CNN's training patient (``${key}`` below stands for it)
TRAINING = "training"
T = "${depth.cnn.checkpoint_patient}"
Q = "${output_dir}/${item.patient}"
S = "${item.sequence}"
E = "${output_dir}/evaluation/${item.patient}/${item.sequence}"

#: the default configuration's sequences (for stages that read all of a patient's sequences)
SEQUENCES = yaml.safe_load((ROOT / "params.yaml").read_text(encoding="utf-8"))["sequences"]

#: name -> (foreach, extra deps, params, outs, metrics file)
STAGES = {
    "phantom": ("${phantoms}", [], ["phantom", "phantoms.${key}"],
                [f"{P}/input/ct.nii.gz", f"{P}/ground_truth"], f"{P}/metrics/phantom.json"),
    "segment": ("${patients}", ["${item.input}"], ["segment", "patients.${key}"],
                [f"{P}/anatomy/airway_mask.nii.gz", f"{P}/anatomy/ct_metadata.json"], f"{P}/metrics/segment.json"),
    "sdf": ("${patients}", [f"{P}/anatomy/airway_mask.nii.gz"], ["sdf"],
            [f"{P}/anatomy/sdf.nii.gz", f"{P}/anatomy/sdf_metadata.json"], f"{P}/metrics/sdf.json"),
    "mesh": ("${patients}", [f"{P}/anatomy/sdf.nii.gz"], ["mesh"],
             [f"{P}/anatomy/lung_model.obj", f"{P}/anatomy/collision_model.obj", f"{P}/anatomy/mesh_metadata.json",
              f"{P}/anatomy/volume_mesh"],
             f"{P}/metrics/mesh.json"),
    "validate_anatomy": ("${phantoms}", [f"{P}/ground_truth", f"{P}/anatomy/airway_mask.nii.gz",
                                         f"{P}/anatomy/sdf.nii.gz", f"{P}/anatomy/lung_model.obj"],
                         ["sdf", "mesh"], [], f"{P}/metrics/anatomy_validation.json"),
    "medial_axis": ("${patients}", [f"{P}/anatomy/sdf.nii.gz"], ["medial_axis"],
                    [f"{P}/anatomy/medial_axis.ply", f"{P}/anatomy/centreline_graph.json"],
                    f"{P}/metrics/medial_axis.json"),
    "validate_centreline": ("${phantoms}", [f"{P}/ground_truth", f"{P}/anatomy/centreline_graph.json"],
                            ["medial_axis"], [], f"{P}/metrics/centreline_validation.json"),
    "trajectory": (MATRIX, [f"{Q}/anatomy/centreline_graph.json", f"{Q}/anatomy/sdf.nii.gz"],
                   # the patient entry: its optional start_pose file (a DVC matrix cannot declare a per-item optional
                   # file dep, iterative/dvc#10094; trajectory.json records the file's sha256)
                   ["trajectory", "sequences", "patients.${item.patient}"],
                   [f"{Q}/{S}/metadata/trajectory.json", f"{Q}/{S}/metadata/timestamps.json",
                    f"{Q}/{S}/metadata/trajectory_tum.txt"], f"{Q}/metrics/trajectory_{S}.json"),
    "simulate": (MATRIX, [f"{Q}/{S}/metadata/trajectory.json", f"{Q}/anatomy/collision_model.obj",
                          f"{Q}/anatomy/mesh_metadata.json",
                          f"{Q}/anatomy/centreline_graph.json"], ["simulate"],
                 [f"{Q}/{S}/metadata/robot_config.json", f"{Q}/{S}/metadata/simulation.json",
                  f"{Q}/{S}/metadata/simulated_tum.txt"], f"{Q}/metrics/simulate_{S}.json"),
    # reads the planned or the simulated poses (render.poses), so both are listed
    "render": (MATRIX, [f"{Q}/{S}/metadata/trajectory.json", f"{Q}/{S}/metadata/simulation.json",
                        f"{Q}/anatomy/lung_model.obj", f"{Q}/anatomy/centreline_graph.json"], ["render"],
               [f"{Q}/{S}/{d}" for d in ("rgb", "depth", "relative_depth", "surface_normals", "optical_flow",
                                         "point_clouds", "segmentation", "calibration")]
               + [f"{Q}/{S}/metadata/render.json"], f"{Q}/metrics/render_{S}.json"),
    "noise": (MATRIX, [f"{Q}/{S}/rgb", "${noise.profile}", "data/noise_profiles"], ["noise"],
              [f"{Q}/{S}/rgb_noisy", f"{Q}/{S}/metadata/noise.json"], f"{Q}/metrics/noise_{S}.json"),
    # reads rgb_noisy (evaluate.pose.images: noisy) or rgb
    "evaluate_pose": (MATRIX, [f"{Q}/{S}/rgb", f"{Q}/{S}/rgb_noisy", f"{Q}/{S}/calibration",
                               f"{Q}/{S}/metadata/render.json", f"{Q}/anatomy/centreline_graph.json"],
                      ["evaluate.pose"],
                      [f"{E}/pose.json", f"{E}/pose_errors.csv"], f"{Q}/metrics/evaluate_pose_{S}.json"),
    # once, for depth.cnn.checkpoint_patient; trains on every configured sequence of it (the list is expanded from params.yaml's
    # `sequences` when this file is generated: rerun this script after changing it; `sequences` is a param)
    "train_depth": (TRAINING, [f"{P}/{s}/{d}" for s in SEQUENCES
                                    for d in ("${depth.input}", "depth", "calibration", "metadata/render.json")],
                    ["depth.train", "depth.cnn", "depth.valid_range_mm", "depth.input", "sequences"],
                    [f"{P}/depth_model", "${output_dir}/evaluation/${key}/depth_finetune.json"],
                    f"{P}/metrics/train_depth.json"),
    "evaluate_depth": (MATRIX, [f"{Q}/{S}/{d}" for d in ("${depth.input}", "depth", "calibration",
                                                            "metadata/render.json")]
                       + ["${output_dir}/${depth.cnn.checkpoint_patient}/depth_model"], ["depth"],
                       [f"{E}/depth.json", f"{E}/depth_errors.csv"], f"{Q}/metrics/evaluate_depth_{S}.json"),
    # once over the dataset: every evaluation result lives under ${output_dir}/evaluation
    "tables": (DATASET, ["${output_dir}/evaluation"], ["evaluate.tables", "evaluate.pose.methods", "depth.cnn.checkpoint_patient",
                                                  "depth.train.eval_patients"],
               [f"reports/{t}.{x}" for t in ("table_1_pose", "table_2_depth", "table_3_finetune")
                for x in ("md", "tex", "csv")] + ["reports/pose_speed_accuracy.csv"], "reports/metrics.json"),
}

HEADER = """\
# Generated by scripts/write_dvc_yaml.py (edit the table there, then rerun it).
# One stage per pipeline step; each lists its code (the sub-packages of `room stage NAME`'s import
# closure as folders, top-level and stage modules as files), its upstream outputs, the params it reads
# and its outs.
# Patients fan out with foreach over `phantoms` / `patients` in params.yaml.
"""


def render() -> str:
    lines = [HEADER.rstrip("\n"), "stages:"]
    for name, (foreach, extra, params, outs, metrics) in STAGES.items():
        if foreach == DATASET:
            ind = "    "
            lines += [f"  {name}:", f"{ind}cmd: room stage {name} --patient all --params params.yaml --quiet"]
        elif foreach == TRAINING:
            ind = "    "
            lines += [f"  {name}:", f"{ind}cmd: room stage {name} --patient {T} --params params.yaml --quiet"]
            extra, outs, metrics = ([x.replace("${key}", T) for x in extra], [x.replace("${key}", T) for x in outs],
                                    metrics.replace("${key}", T))
        elif foreach == MATRIX:
            ind = "    "
            lines += [f"  {name}:", "    matrix:", "      patient: ${patients}", "      sequence: ${sequences}",
                      f"{ind}cmd: room stage {name} --patient ${{item.patient}}/${{item.sequence}} "
                      "--params params.yaml --quiet"]
        else:
            ind = "      "
            lines += [f"  {name}:", f"    foreach: {foreach}", "    do:",
                      f"{ind}cmd: room stage {name} --patient ${{key}} --params params.yaml --quiet"]
        lines += [f"{ind}deps:"] + [f"{ind}  - {d}" for d in extra + package_deps(name)]
        lines += [f"{ind}params:"] + [f"{ind}  - {p}" for p in params]
        plots = [o for o in outs if o.endswith("_errors.csv")]     # per-frame errors: DVC plots
        outs = [o for o in outs if o not in plots]
        # a stage's timings (room_pipeline.io.metrics): an uncached out, not a metric, so that
        # `dvc exp show --only-changed` compares accuracy only
        timing = [metrics[:-len(".json")] + ".timing.json"]
        if outs or timing:
            lines += [f"{ind}outs:"]
            for o in outs:   # the dataset-level report tables belong in git, not the DVC cache
                lines += [f"{ind}  - {o}:", f"{ind}      cache: false"] if foreach == DATASET else [f"{ind}  - {o}"]
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
