"""Stage `evaluate_depth`: one rendered sequence -> monocular depth accuracy and speed of every method (Table II).

Reads ``<patient>/<sequence>/{rgb|rgb_noisy}/frame_NNNN.png``, ``depth/frame_NNNN.exr``,
``calibration/camera_params.json`` and ``metadata/render.json`` (the light model
of the physics baseline) and, for the CNN rows, the checkpoints of the
``train_depth`` stage of ``depth.cnn.checkpoint_patient``.  Writes

``<output_dir>/evaluation/<patient>/<sequence>/depth.json``
    ``{"methods": {name: {"available", "reason", "L1_mm", "AbsRel", "RMSE_mm",
    "delta1", "delta2", "delta3", "n_frames", "seconds_per_frame", "scaling",
    ...}}, "units": {...}, "valid_range_mm": [lo, hi], ...}``: one row per
    method in its own scaling, plus ``<name>_median`` for metric methods
    (``depth.also_median``).  An unavailable method (package, weights or
    predictions missing) has ``available: false``, the reason and null numbers.
``<output_dir>/evaluation/<patient>/<sequence>/depth_errors.csv``
    one line per frame: ``frame`` then ``<row>_<metric>`` for every available
    row (metrics of :mod:`room_pipeline.depth.metrics`) and ``<row>_seconds``.
``<patient>/metrics/evaluate_depth_<sequence>.json``
    a short summary (AbsRel, delta1, L1, seconds per frame per row; wall time).
"""
from __future__ import annotations

import io
import math
import time
from pathlib import Path

from omegaconf import DictConfig

from ..catalog import split_key
from ..config.compose import section
from ..depth.estimators import (ORACLES, TRAINED_ON_CHECKPOINT_PATIENT, DepthParams, SequenceInfo, evaluate,
                                sequence_samples, try_create)
from ..depth.metrics import METRIC_KEYS, UNITS
from ..evaluate.allocator import keep_freed_memory
from ..io.atomic import write_json, write_text
from .common import StageTimer, _finite, metadata, patient_paths, read_json, round_floats, write_metrics


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    paths = patient_paths(cfg, patient)
    ev = paths.eval(sequence)
    return [ev.depth, ev.depth_errors, paths.metrics(f"evaluate_depth_{sequence}")]


def declared_scaling(name: str, p: DepthParams) -> str:
    """The scaling a method would be evaluated in, known without loading it."""
    if name == "physics":
        return "metric"
    if name in ("cnn", "cnn_pretrained"):
        return "median"
    spec = (p.hf or {}).get(name) or (p.external or {}).get(name) or {}
    return spec.get("scaling", "median") if isinstance(spec, dict) else "median"


def _nan_row(scaling: str, reason: str) -> dict:
    return {"available": False, "reason": reason, **{k: None for k in METRIC_KEYS}, "n_frames": 0,
            "seconds_per_frame": None, "scaling": scaling}


def errors_csv(rows: dict, frame_names: list) -> str:
    """Per-frame CSV text: frame, then <row>_<metric> and <row>_seconds for every row."""
    cols = ["frame"]
    for name in rows:
        cols += [f"{name}_{k}" for k in METRIC_KEYS] + [f"{name}_n_valid", f"{name}_seconds"]
    out = io.StringIO()
    out.write(",".join(cols) + "\n")

    def fmt(x) -> str:
        return "" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.6g}"

    for i, frame in enumerate(frame_names):
        vals = [frame]
        for row in rows.values():
            fe = row.frames[i]
            vals += [fmt(getattr(fe, k)) for k in METRIC_KEYS] + [str(fe.n_valid), fmt(row.seconds[i])]
        out.write(",".join(vals) + "\n")
    return out.getvalue()


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
        estimators, unavailable, described = {}, {}, {}
        for name in p.methods:
            if name in TRAINED_ON_CHECKPOINT_PATIENT and patient == p.cnn.checkpoint_patient:
                unavailable[name] = (f"in-sample: fitted on {patient}'s frames (depth.cnn.checkpoint_patient), so "
                                     "not scored on them (Table II scores only data never trained on)")
                continue
            est, reason = try_create(name, p, info)
            if est is None:
                unavailable[name] = reason
            else:
                estimators[name] = est
                described[name] = est.describe()
        try:
            rows = evaluate(estimators, samples, p.valid_range_m, also_median=p.also_median)
        finally:
            for est in estimators.values():
                est.close()
    methods: dict = {}
    for name, row in rows.items():
        methods[name] = {"available": True, "reason": None, **row.summary(), "oracle": row.method in ORACLES}
    for name, reason in unavailable.items():
        sc = declared_scaling(name, p)
        methods[name] = {**_nan_row(sc, reason), "oracle": name in ORACLES}
        if sc == "metric" and p.also_median:
            methods[f"{name}_median"] = {**_nan_row("median", reason), "oracle": name in ORACLES}
    lo, hi = (float(x) for x in p.valid_range_mm)
    ev = paths.eval(sequence)
    doc = {"methods": round_floats(methods, 6), "units": UNITS, "valid_range_mm": [lo, hi],
           "n_frames": len(samples), "frames": [s.name for s in samples], "input": p.input,
           "estimators": described, "wall_time_s": round(timer.wall_s, 3),
           "oracle": "rows with oracle: true read the renderer's light model (power, albedo, exposure)",
           "protocol": "frame-averaged metrics on pixels with ground truth in valid_range_mm and a finite positive "
                       "prediction; 'median' rows scaled once per sequence by median(gt) / median(pred)",
           "metadata": metadata("evaluate_depth", patient, cfg, ("depth",), sequence=sequence)}
    write_json(ev.depth, _finite(doc))
    write_text(ev.depth_errors, errors_csv(rows, [s.name for s in samples]))
    summary = {name: {k: m.get(k) for k in ("AbsRel", "delta1", "L1_mm", "seconds_per_frame")}
               for name, m in methods.items() if m["available"]}
    metrics = {"frames": len(samples), "methods_available": len(rows), "methods_unavailable": len(unavailable),
               "wall_time_s": round(timer.wall_s, 3), "cpu_time_s": round(time.process_time() - cpu0, 3),
               "seconds_per_frame_all_methods": round(timer.wall_s / len(samples), 4),
               "peak_rss_mb": round(timer.peak_rss_mb(), 1), "methods": round_floats(summary, 6)}
    write_metrics(paths, f"evaluate_depth_{sequence}", metrics)
    return metrics
