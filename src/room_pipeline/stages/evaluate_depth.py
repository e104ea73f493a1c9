"""Stage `evaluate_depth`: one rendered sequence -> monocular depth accuracy and speed of every method (Table II).

Reads ``<patient>/<sequence>/{rgb|rgb_noisy}/frame_NNNN.png``, ``depth/frame_NNNN.exr``,
``calibration/camera_params.json`` and ``metadata/render.json`` (the light model
of the physics baseline) and, for the CNN rows, the checkpoints of the
``train_depth`` stage of ``depth.cnn.checkpoint_patient``.  Writes

``<output_dir>/evaluation/<patient>/<sequence>/depth.json``
    ``{"methods": {name: {"available", "reason", "L1_mm", "AbsRel", "RMSE_mm",
    "delta1", "delta2", "delta3", "n_frames", "scaling", ...}}, "units": {...},
    "valid_range_mm": [lo, hi], ...}``: one row per
    method in its own scaling, plus ``<name>_median`` for metric methods
    (``depth.also_median``).  An unavailable method (package, weights or
    predictions missing) has ``available: false``, the reason and null numbers.
``<output_dir>/evaluation/<patient>/<sequence>/depth_errors.csv``
    one line per frame: ``frame`` then ``<row>_<metric>`` for every available
    row (metrics of :mod:`room_pipeline.depth.metrics`).
``<patient>/metrics/evaluate_depth_<sequence>.json``
    a short summary (AbsRel, delta1, L1 per row); its ``.timing.json`` holds every timing (stage wall / CPU
    time, and under ``methods.<row>`` the seconds per frame, CPU seconds per frame and ``frame_seconds``):
    the data files above hold none, so the same inputs give the same bytes.
"""
from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig

from ..catalog import split_key
from ..config.compose import section
from ..depth.estimators import DepthParams, SequenceInfo, evaluate, sequence_samples
from ..depth.sequence_eval import create_estimators, depth_document, depth_summary, errors_csv, method_rows
from ..evaluate.allocator import keep_freed_memory
from ..io.atomic import write_json, write_text
from .common import StageTimer, metadata, patient_paths, read_json, without_timings, write_metrics


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    paths = patient_paths(cfg, patient)
    ev = paths.eval(sequence)
    return [ev.depth, ev.depth_errors, paths.stage_metrics("evaluate_depth", sequence)]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = DepthParams.from_dict(section(cfg, "depth"))
    paths = patient_paths(cfg, patient)
    seq = paths.sequence(sequence)
    keep_freed_memory()          # full-frame temporaries: no page-fault churn (evaluate/allocator.py)
    cpu0 = time.process_time()
    with StageTimer() as timer:
        samples = sequence_samples(seq, p.input, p.frame_stride, p.max_frames, group=key)
        render_json = paths.seq(sequence).render_json
        renderer = read_json(render_json).get("renderer") if render_json.is_file() else None
        info = SequenceInfo(camera=samples[0].camera, root=seq, patient=patient, sequence=sequence,
                            renderer=renderer, output_dir=Path(cfg.output_dir))
        estimators, unavailable, described = create_estimators(p, info, patient)
        try:
            rows = evaluate(estimators, samples, p.valid_range_m, also_median=p.also_median)
        finally:
            for est in estimators.values():
                est.close()
    methods = method_rows(rows, unavailable, p)
    ev = paths.eval(sequence)
    meta = metadata("evaluate_depth", patient, cfg, ("depth",), sequence=sequence)
    doc, doc_timings = without_timings(depth_document(methods, samples, p, described, meta, rows))
    write_json(ev.depth, doc)
    write_text(ev.depth_errors, errors_csv(rows, [s.name for s in samples]))
    metrics = {"frames": len(samples), "methods_available": len(rows), "methods_unavailable": len(unavailable),
               "wall_time_s": round(timer.wall_s, 3), "cpu_time_s": round(time.process_time() - cpu0, 3),
               "seconds_per_frame_all_methods": round(timer.wall_s / len(samples), 4),
               "peak_rss_mb": round(timer.peak_rss_mb(), 1), "methods": depth_summary(methods)}
    write_metrics(paths, "evaluate_depth", metrics, doc_timings, sequence)
    return metrics
