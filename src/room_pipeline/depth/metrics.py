"""Monocular depth error metrics (pure numpy), as in the ROOM paper's Tables II and III.

Valid pixels
    ground truth finite and inside ``valid_range_m = (lo, hi)`` (metres; the
    renderer's 0 = no hit is outside any positive range) **and** prediction
    finite and > 0.  GT-valid pixels whose prediction is NaN/inf are counted in
    ``n_nonfinite``, those with a prediction <= 0 in ``n_nonpositive``; both are
    left out of the errors and reported, never silently filled.

Per frame (on the valid pixels, prediction ``p`` times ``scale``, ground truth ``g``)
    ``L1_mm`` = mean |p - g| (mm), ``AbsRel`` = mean |p - g| / g,
    ``RMSE_mm`` = sqrt(mean (p - g)^2) (mm), ``delta_i`` = fraction with
    max(p/g, g/p) < 1.25^i, i = 1, 2, 3.  No valid pixel: every error is NaN and
    ``n_valid`` is 0 (no exception).

Sequence
    The mean of the per-frame metrics over the frames with at least one valid
    pixel (frame-averaged, as the SimCol and KITTI protocols do).

Median scaling ("relative" methods)
    One scale per sequence, ``s = median(g) / median(p)`` over the valid pixels
    of all its frames (the paper's protocol).  The medians are streamed through
    a fine histogram of log values (:class:`LogMedian`, bin 1e-4 in log, i.e.
    0.01 % relative), so a long sequence needs no memory for them.

Shapes
    A prediction must have the ground truth's (H, W); otherwise
    :func:`check_shape` raises :class:`~room_pipeline.errors.InputError` naming
    both shapes.  Only an estimator that declares it works at its own
    resolution gets resized (:func:`fit_to_shape`), never silently.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError

#: the metric keys, in table order
METRIC_KEYS = ("L1_mm", "AbsRel", "RMSE_mm", "delta1", "delta2", "delta3")
UNITS = {"L1_mm": "mm", "AbsRel": "1 (fraction)", "RMSE_mm": "mm", "delta1": "fraction, max(p/g, g/p) < 1.25",
         "delta2": "fraction, < 1.25^2", "delta3": "fraction, < 1.25^3", "seconds_per_frame": "s",
         "valid_range_mm": "mm"}
DELTA_BASE = 1.25


@dataclasses.dataclass(frozen=True)
class FrameErrors:
    """One frame's errors (NaN when ``n_valid`` is 0) and pixel counts."""

    L1_mm: float
    AbsRel: float
    RMSE_mm: float
    delta1: float
    delta2: float
    delta3: float
    n_valid: int          # pixels used
    n_gt: int             # pixels with ground truth in range
    n_nonfinite: int      # ... of which the prediction is NaN or inf
    n_nonpositive: int    # ... of which the prediction is finite but <= 0

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def check_shape(gt_shape: tuple, pred_shape: tuple, where: str = "") -> None:
    """InputError unless the prediction has the ground truth's (H, W)."""
    if tuple(pred_shape) != tuple(gt_shape):
        at = f"{where}: " if where else ""
        raise InputError(f"{at}predicted depth has shape {tuple(pred_shape)}, ground truth {tuple(gt_shape)} "
                         "(no silent resize: the estimator must declare that it resizes)")


def fit_to_shape(pred: np.ndarray, shape: tuple, resizes: bool, where: str = "") -> np.ndarray:
    """``pred`` as float32 of ``shape``: bilinear resize only when ``resizes`` (else :func:`check_shape`).

    Non-finite values stay invalid after resizing: they are resized as a mask
    and every output pixel touched by one becomes NaN.
    """
    p = np.asarray(pred, dtype=np.float32)
    if p.ndim != 2:
        raise InputError(f"{where + ': ' if where else ''}predicted depth must be (H, W), got shape {p.shape}")
    if p.shape == tuple(shape):
        return p
    if not resizes:
        check_shape(shape, p.shape, where)
    import cv2

    bad = ~np.isfinite(p)
    src = np.where(bad, 0.0, p).astype(np.float32)
    out = cv2.resize(src, (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
    if bad.any():
        spread = cv2.resize(bad.astype(np.float32), (int(shape[1]), int(shape[0])), interpolation=cv2.INTER_LINEAR)
        out[spread > 0] = np.nan
    return out


def valid_gt(gt: np.ndarray, valid_range_m: Sequence[float]) -> np.ndarray:
    """Pixels whose ground truth is finite and within [lo, hi] metres."""
    g = np.asarray(gt)
    lo, hi = float(valid_range_m[0]), float(valid_range_m[1])
    with np.errstate(invalid="ignore"):
        return np.isfinite(g) & (g >= lo) & (g <= hi)


def valid_pixels(gt: np.ndarray, pred: np.ndarray, valid_range_m: Sequence[float],
                 g_ok: np.ndarray | None = None) -> tuple[np.ndarray, int, int]:
    """(mask of usable pixels, n_nonfinite, n_nonpositive) -- see the module docstring.  ``g_ok``: the
    ``valid_gt`` mask when the caller already has it."""
    if g_ok is None:
        g_ok = valid_gt(gt, valid_range_m)
    p = np.asarray(pred)
    finite = np.isfinite(p)
    with np.errstate(invalid="ignore"):
        positive = p > 0
    n_nonfinite = int(np.count_nonzero(g_ok & ~finite))
    n_nonpositive = int(np.count_nonzero(g_ok & finite & ~positive))
    return g_ok & finite & positive, n_nonfinite, n_nonpositive


def frame_errors(gt: np.ndarray, pred: np.ndarray, valid_range_m: Sequence[float], scale: float = 1.0,
                 where: str = "") -> FrameErrors:
    """Errors of one predicted depth map (metres, times ``scale``) against the ground truth (metres)."""
    g_all = np.asarray(gt)
    p_all = np.asarray(pred)
    check_shape(g_all.shape, p_all.shape, where)
    g_ok = valid_gt(g_all, valid_range_m)
    mask, n_nonfinite, n_nonpositive = valid_pixels(g_all, p_all, valid_range_m, g_ok)
    n_gt = int(np.count_nonzero(g_ok))
    n = int(np.count_nonzero(mask))
    if n == 0:
        nan = math.nan
        return FrameErrors(nan, nan, nan, nan, nan, nan, 0, n_gt, n_nonfinite, n_nonpositive)
    g = g_all[mask].astype(np.float64)
    p = p_all[mask].astype(np.float64) * float(scale)
    diff = p - g
    ad = np.abs(diff)
    ratio = np.maximum(p / g, g / p)
    return FrameErrors(
        L1_mm=float(ad.mean() * 1e3), AbsRel=float((ad / g).mean()), RMSE_mm=float(np.sqrt((diff * diff).mean()) * 1e3),
        delta1=float((ratio < DELTA_BASE).mean()), delta2=float((ratio < DELTA_BASE ** 2).mean()),
        delta3=float((ratio < DELTA_BASE ** 3).mean()),
        n_valid=n, n_gt=n_gt, n_nonfinite=n_nonfinite, n_nonpositive=n_nonpositive)


def aggregate(frames: Iterable[FrameErrors]) -> dict:
    """Sequence metrics: the mean of each metric over frames with valid pixels; NaN when there is none.

    Also ``n_frames`` (all frames), ``n_frames_valid`` and the summed pixel counts.
    """
    frames = list(frames)
    used = [f for f in frames if f.n_valid > 0]
    out: dict = {}
    for k in METRIC_KEYS:
        out[k] = float(np.mean([getattr(f, k) for f in used])) if used else math.nan
    out.update(n_frames=len(frames), n_frames_valid=len(used),
               n_valid_pixels=int(sum(f.n_valid for f in frames)),
               n_nonfinite_pixels=int(sum(f.n_nonfinite for f in frames)),
               n_nonpositive_pixels=int(sum(f.n_nonpositive for f in frames)))
    return out


class LogMedian:
    """Streaming median of positive values through a histogram of their natural log.

    Bins of ``bin_width`` (1e-4: 0.01 % relative) over ``[log_lo, log_hi]``;
    values outside are clamped into the end bins.  Deterministic and exact to
    half a bin.
    """

    def __init__(self, log_lo: float = -25.0, log_hi: float = 25.0, bin_width: float = 1e-4) -> None:
        self.log_lo, self.bin_width = float(log_lo), float(bin_width)
        self.n_bins = int(math.ceil((log_hi - log_lo) / bin_width))
        self.counts = np.zeros(self.n_bins, dtype=np.int64)
        self.n = 0

    def add(self, values: np.ndarray) -> None:
        v = np.asarray(values, dtype=np.float64).ravel()
        if v.size == 0:
            return
        idx = np.floor((np.log(v) - self.log_lo) / self.bin_width).astype(np.int64)
        np.clip(idx, 0, self.n_bins - 1, out=idx)
        lo = int(idx.min())             # count over the occupied span only (not a 500k-bin array per call)
        idx -= lo
        span = np.bincount(idx)
        self.counts[lo:lo + span.size] += span
        self.n += v.size

    def median(self) -> float:
        """The median (NaN when empty), interpolated linearly in log inside its bin."""
        if self.n == 0:
            return math.nan
        cum = np.cumsum(self.counts)
        half = 0.5 * self.n
        b = int(np.searchsorted(cum, half))
        below = cum[b - 1] if b > 0 else 0
        frac = (half - below) / max(int(self.counts[b]), 1)
        return float(math.exp(self.log_lo + (b + frac) * self.bin_width))


class MedianScaler:
    """Accumulates the valid pixels of a sequence; ``scale()`` = median(gt) / median(pred)."""

    def __init__(self, valid_range_m: Sequence[float]) -> None:
        self.valid_range_m = tuple(float(x) for x in valid_range_m)
        self.gt = LogMedian()
        self.pred = LogMedian()

    def add(self, gt: np.ndarray, pred: np.ndarray) -> None:
        mask, _, _ = valid_pixels(gt, pred, self.valid_range_m)
        self.gt.add(np.asarray(gt)[mask])
        self.pred.add(np.asarray(pred)[mask])

    def scale(self) -> float:
        """NaN when no frame had a valid pixel."""
        g, p = self.gt.median(), self.pred.median()
        return g / p if (math.isfinite(g) and math.isfinite(p) and p > 0) else math.nan


def median_scale(gts: Sequence[np.ndarray], preds: Sequence[np.ndarray], valid_range_m: Sequence[float]) -> float:
    """Exact per-sequence scale median(g) / median(p) over all valid pixels (small data: tests, training)."""
    gv, pv = [], []
    for g, p in zip(gts, preds):
        m, _, _ = valid_pixels(g, p, valid_range_m)
        gv.append(np.asarray(g, np.float64)[m])
        pv.append(np.asarray(p, np.float64)[m])
    g = np.concatenate(gv) if gv else np.zeros(0)
    p = np.concatenate(pv) if pv else np.zeros(0)
    if g.size == 0:
        return math.nan
    return float(np.median(g) / np.median(p))
