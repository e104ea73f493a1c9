"""The pixel filter of the fast renderer: a pixel's value integrated over its footprint where one ray is not enough.

A camera pixel (and a Cycles pixel) does not record the radiance along the ray through its centre but the
radiance weighted over the pixel's footprint on the image plane by a pixel filter.  Cycles' default filter
is a separable Blackman-Harris window of width ``w`` = 1.5 px (``CyclesSettings.filter_width``; in 1D
``B(x) = 0.35875 - 0.48829 cos(t) + 0.14128 cos(2t) - 0.01168 cos(3t)``, ``t = 2 pi (x / w + 1/2)``,
``|x| < w / 2``, x in pixels), importance-sampled: each sample's offset from the pixel centre is drawn from
``B`` in x and in y independently, and the pixel is their plain mean.

Where the radiance is smooth over the footprint the filter changes little (its standard deviation is
0.2 px), and the ray caster's one ray through the pixel centre is what the filter returns.  Where a
**silhouette** crosses the footprint (a fold's or the carina's edge in front of a farther wall, the lumen's
dark opening) the filter mixes two surfaces whose radiance differs many-fold, and a centre ray picks one of
them: the error is of the order of the contrast, at every such pixel.  :func:`silhouette_pixels` finds those
pixels from the frame's own depth (a jump in the second difference of 1/depth, or hit next to no hit), and
:func:`filter_offsets` gives ``m x m`` sub-pixel offsets at the quantiles of ``B`` (deterministic, equal
weights: the same estimator as Cycles' importance sampling, stratified); the renderer shades them there and
averages (:meth:`room_pipeline.render.raycast.RaycastRenderer.render`, ``RaycastConfig.edge_samples``).

Measured against Cycles (``benchmarks/results/cycles_residual_s11.md``, 200x200 whole frames): silhouettes are
0.2-0.8 % of the pixels and 1-5 % of the squared error; ``edge_samples`` 3 gains 0.0-0.26 dB PSNR*, every pixel
integrated (3x3) 0.3-0.5 dB: the pixel filter is not what keeps the default RGB from Cycles, so it is off by default.
"""
from __future__ import annotations

import numpy as np

#: Cycles' default pixel filter width (Blackman-Harris), px
FILTER_WIDTH_PX = 1.5


def blackman_harris(x: np.ndarray, width: float = FILTER_WIDTH_PX) -> np.ndarray:
    """Cycles' Blackman-Harris pixel filter at offsets ``x`` (px) from the pixel centre (0 for ``|x| >= width/2``)."""
    x = np.asarray(x, dtype=np.float64)
    t = 2 * np.pi * (x / width + 0.5)
    b = 0.35875 - 0.48829 * np.cos(t) + 0.14128 * np.cos(2 * t) - 0.01168 * np.cos(3 * t)
    return np.where(np.abs(x) < width / 2, b, 0.0)


def filter_quantiles(m: int, width: float = FILTER_WIDTH_PX, n: int = 4097) -> np.ndarray:
    """(m,) offsets (px) at the quantiles ``(k + 1/2) / m`` of the 1D filter's distribution (symmetric about 0)."""
    if m < 1:
        raise ValueError(f"filter samples per axis must be >= 1, got {m}")
    x = np.linspace(-width / 2, width / 2, n)
    cdf = np.cumsum(blackman_harris(x, width))
    cdf = (cdf - cdf[0]) / (cdf[-1] - cdf[0])
    q = np.interp((np.arange(m) + 0.5) / m, cdf, x)
    return 0.5 * (q - q[::-1])                           # exactly symmetric


def filter_offsets(m: int, width: float = FILTER_WIDTH_PX) -> np.ndarray:
    """(m * m, 2) sub-pixel offsets (du, dv) in px: the product of :func:`filter_quantiles` in u and v."""
    q = filter_quantiles(m, width)
    du, dv = np.meshgrid(q, q)
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def silhouette_pixels(depth: np.ndarray, hit: np.ndarray, jump: float) -> np.ndarray:
    """(H, W) bool: pixels at a depth discontinuity, or with hits and no-hits among their 8 neighbours.

    The inverse planar depth ``1/z`` of a plane is affine in the pixel coordinates, so its second difference
    along a row or a column, ``|w(x-1) - 2 w(x) + w(x+1)|``, vanishes on smooth walls (however grazing) and
    is of the order of the jump where one surface passes behind another; a pixel is a silhouette where it
    exceeds ``jump`` x the largest of the three ``w`` (a relative jump of ~``jump``).
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    w = np.where(hit, 1.0 / np.where(hit, depth, 1.0), 0.0).astype(np.float32)
    h8 = hit.astype(np.uint8)
    out = maximum_filter(h8, size=3, mode="nearest") != minimum_filter(h8, size=3, mode="nearest")
    for ax in (0, 1):
        p = np.pad(w, [(1, 1) if a == ax else (0, 0) for a in (0, 1)], mode="edge")
        lo, mid, hi = (np.take(p, np.arange(k, k + w.shape[ax]), axis=ax) for k in (0, 1, 2))
        out |= np.abs(lo - 2 * mid + hi) > np.float32(jump) * np.maximum(np.maximum(lo, mid), hi)
    return out
