"""Stage `evaluate_pose`: one rendered sequence -> multi-view pose accuracy of each configured method (Table I).

Reads ``<patient>/<sequence>/``: the frames (``rgb_noisy/`` when
``evaluate.pose.images`` is ``noisy`` and the noise stage wrote it, else
``rgb/``), the ground-truth camera-to-world poses (``metadata/render.json``)
and the intrinsics (``calibration/camera_params.json``).  Optional frame
stride, frame cap and image downscale (K scaled to match) keep it fast
(:mod:`room_pipeline.evaluate.pose_eval`).

Writes ``<output_dir>/evaluation/<patient>/<sequence>/pose.json`` -- per method: available
/ reason, RRA@5, RTA@5, AUC@30 (fractions of frame pairs), registration rate,
ATE after Sim(3) alignment (mm); no timing: each method's wall / CPU time goes to the stage's
``metrics/evaluate_pose_<sequence>.timing.json`` under ``methods`` (:func:`room_pipeline.io.metrics.read_with_timings`) -- and
``evaluation/pose_errors.csv`` (one row per frame, one column group per method:
registered, position / orientation error after alignment, error of the step
from the previous frame) for ``dvc plots``; DVC metrics in
``metrics/evaluate_pose_<sequence>.json``.
"""
from __future__ import annotations

import time

from omegaconf import DictConfig

from ..anatomy.centreline import CentrelineGraph
from ..catalog import split_key
from ..config.compose import section
from ..errors import InputError
from ..evaluate.allocator import keep_freed_memory
from ..evaluate.pose_eval import (PoseEvalParams, errors_csv, evaluate_methods, load_sequence, pose_document,
                                  pose_summary)
from ..evaluate.route_segments import label_frames
from ..io.atomic import write_json, write_text
from .common import StageTimer, metadata, patient_paths, read_json, without_timings, write_metrics


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    ev = patient_paths(cfg, patient).eval(sequence)
    return [ev.pose, ev.pose_errors]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = PoseEvalParams.from_dict((section(cfg, "evaluate") or {}).get("pose"))
    paths = patient_paths(cfg, patient)
    seq = paths.sequence(sequence)
    keep_freed_memory()          # per-frame temporaries: no page-fault churn (evaluate/allocator.py)
    cpu0 = time.process_time()
    with StageTimer() as timer:
        images, K, poses_gt, info = load_sequence(seq, p)
        graph_file = paths.centreline_graph
        if not graph_file.is_file():
            raise InputError(f"{graph_file} not found (run the medial_axis stage first): needed for the "
                             "per-segment scores")
        labels, regions = label_frames(poses_gt[:, :3, 3], CentrelineGraph.from_dict(read_json(graph_file)),
                                       p.bifurcation_radius_factor)
        results, curves = evaluate_methods(images, K, poses_gt, p, labels)
    meta = metadata("evaluate_pose", patient, cfg, ("evaluate",), sequence=sequence)
    doc, doc_timings = without_timings(pose_document(results, info, labels, regions, p, meta))
    write_json(paths.eval(sequence).pose, doc)
    write_text(paths.eval(sequence).pose_errors, errors_csv(info["frames"], curves))
    metrics = {"frames": len(images), "wall_time_s": round(timer.wall_s, 3),
               "cpu_time_s": round(time.process_time() - cpu0, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1),
               **pose_summary(results, p)}
    write_metrics(paths, "evaluate_pose", metrics, doc_timings, sequence)
    return metrics
