"""Monocular depth evaluation of one rendered sequence (paper Table II): the methods, their rows, the records.

:func:`create_estimators` builds every configured method that can run on the sequence (the rest with
the reason); :func:`method_rows` turns the evaluated rows and the unavailable methods into ``depth.json``'s
``methods`` (:func:`depth_document`), one per method in its own scaling plus ``<name>_median`` for metric
methods; :func:`errors_csv` is the per-frame CSV.
"""
from __future__ import annotations

import io
import math
from typing import Any

from ..io.jsondoc import round_floats
from .estimators import ORACLES, TRAINED_ON_CHECKPOINT_PATIENT, DepthParams, SequenceInfo, try_create
from .metrics import METRIC_KEYS, UNITS


def declared_scaling(name: str, p: DepthParams) -> str:
    """The scaling a method would be evaluated in, known without loading it."""
    if name == "physics":
        return "metric"
    if name in ("cnn", "cnn_pretrained"):
        return "median"
    spec = (p.hf or {}).get(name) or (p.external or {}).get(name) or {}
    return spec.get("scaling", "median") if isinstance(spec, dict) else "median"


def nan_row(scaling: str, reason: str) -> dict:
    return {"available": False, "reason": reason, **{k: None for k in METRIC_KEYS}, "n_frames": 0,
            "seconds_per_frame": None, "scaling": scaling}


def errors_csv(rows: dict, frame_names: list) -> str:
    """Per-frame CSV text: frame, then <row>_<metric> and <row>_n_valid for every row (no times: the per-frame
    seconds are ``frame_seconds`` in :func:`depth_document`, which the stage moves to its timing file)."""
    cols = ["frame"]
    for name in rows:
        cols += [f"{name}_{k}" for k in METRIC_KEYS] + [f"{name}_n_valid"]
    out = io.StringIO()
    out.write(",".join(cols) + "\n")

    def fmt(x) -> str:
        return "" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.6g}"

    for i, frame in enumerate(frame_names):
        vals = [frame]
        for row in rows.values():
            fe = row.frames[i]
            vals += [fmt(getattr(fe, k)) for k in METRIC_KEYS] + [str(fe.n_valid)]
        out.write(",".join(vals) + "\n")
    return out.getvalue()


def create_estimators(p: DepthParams, info: SequenceInfo, patient: str) -> tuple[dict, dict, dict]:
    """({name: estimator}, {name: why unavailable}, {name: description}) of ``depth.methods`` on ``patient``'s
    sequence; a method fitted on the checkpoint patient is never scored on it."""
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
    return estimators, unavailable, described


def method_rows(rows: dict, unavailable: dict, p: DepthParams) -> dict:
    """``depth.json``'s methods: the evaluated rows, then a null row (and its ``_median``) per unavailable one."""
    methods: dict = {}
    for name, row in rows.items():
        methods[name] = {"available": True, "reason": None, **row.summary(), "oracle": row.method in ORACLES}
    for name, reason in unavailable.items():
        sc = declared_scaling(name, p)
        methods[name] = {**nan_row(sc, reason), "oracle": name in ORACLES}
        if sc == "metric" and p.also_median:
            methods[f"{name}_median"] = {**nan_row("median", reason), "oracle": name in ORACLES}
    return methods


def depth_document(methods: dict, samples: list, p: DepthParams, described: dict, metadata: dict,
                   rows: dict | None = None) -> dict:
    """``depth.json`` (before NaN -> null): methods, units, valid range, frames, protocol, provenance; with the
    evaluated ``rows``, each method's per-frame wall seconds as ``methods.<row>.frame_seconds`` (a timing key
    of :data:`room_pipeline.io.metrics.TIMING_KEYS`: the stage moves it to its timing file)."""
    lo, hi = (float(x) for x in p.valid_range_mm)
    methods = {name: {**m, "frame_seconds": [float(x) for x in rows[name].seconds]} if name in (rows or {}) else m
               for name, m in methods.items()}
    return {"methods": round_floats(methods, 6), "units": UNITS, "valid_range_mm": [lo, hi],
            "n_frames": len(samples), "frames": [s.name for s in samples], "input": p.input,
            "estimators": described,
            "oracle": "rows with oracle: true read the renderer's light model (power, albedo, exposure)",
            "protocol": "frame-averaged metrics on pixels with ground truth in valid_range_mm and a finite positive "
                        "prediction; 'median' rows scaled once per sequence by median(gt) / median(pred)",
            "metadata": metadata}


def depth_summary(methods: dict) -> dict[str, Any]:
    """{row: AbsRel, delta1, L1, seconds per frame} of the available rows (the DVC metrics)."""
    return round_floats({name: {k: m.get(k) for k in ("AbsRel", "delta1", "L1_mm", "seconds_per_frame")}
                         for name, m in methods.items() if m["available"]}, 6)
