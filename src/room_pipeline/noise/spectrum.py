"""Power spectra of image noise: estimation, resampling, radial averages, spectral distance.

Conventions used by the whole :mod:`room_pipeline.noise` package:

Frequency grid
    Normalised spatial frequency ``f = (fy, fx)`` in cycles per pixel, each in
    ``[-0.5, 0.5)``; 2-D arrays over a grid are in FFT order (``np.fft.fftfreq``),
    so index ``k`` of an axis of length ``n`` is ``f = k / n`` (wrapped).

PSD normalisation
    A power spectral density ``S(f)`` is *per unit frequency area*: its
    integral over the unit frequency square is the variance,
    ``integral S(f) df = sigma^2``.  On a uniform ``n x m`` grid the integral is
    the grid mean, so ``S.mean() == variance``.  With intensities in 8-bit
    levels, ``S`` is in levels^2 per (cycle/pixel)^2.  This makes spectra of
    frames of different sizes comparable bin by bin, and keeps the variance
    when a spectrum is resampled to another grid.

Cross-spectral matrix
    For a C-channel field, ``S[c, d](f) = E[X_c(f) conj(X_d(f))] / norm`` with
    ``X`` the DFT; ``S[c, c]`` are the per-channel PSDs, ``S[c, d]`` the
    complex cross spectra; ``S(-f) = conj(S(f))`` for real fields.  Its grid
    mean is the zero-lag covariance matrix of the channels.

Log-spectral distance (LSD)
    Between two radially averaged PSDs ``a`` and ``b`` on the same radial bins:
    ``LSD = sqrt(mean_bins (10 log10(a / b))^2)`` in dB, over the bins with
    ``0 < |f| <= 0.5`` (the DC bin and the corners beyond the Nyquist circle
    are left out), and over channels when the spectra have several (the RMS is
    taken over every (channel, bin) pair).  0 dB is identity; 1 dB is an RMS
    power ratio of about 1.26.
"""
from __future__ import annotations

import functools

import numpy as np

#: default number of radial bins between 0 and the Nyquist frequency 0.5 cycles/pixel
RADIAL_BINS = 32


@functools.lru_cache(maxsize=8)
def hann2d(n: int) -> np.ndarray:
    """Separable periodic Hann window ``(n, n)``, float64."""
    w = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n)
    return np.outer(w, w)


def tile_origins(valid: np.ndarray, tile: int, step: int) -> list[tuple[int, int]]:
    """Top-left corners of the ``tile x tile`` windows on a ``step`` grid whose pixels are all valid."""
    h, w = valid.shape
    if h < tile or w < tile:
        return []
    integral = np.zeros((h + 1, w + 1), np.int64)
    integral[1:, 1:] = np.cumsum(np.cumsum(valid.astype(np.int64), 0), 1)
    out = []
    for y in range(0, h - tile + 1, step):
        for x in range(0, w - tile + 1, step):
            s = integral[y + tile, x + tile] - integral[y, x + tile] - integral[y + tile, x] + integral[y, x]
            if s == tile * tile:
                out.append((y, x))
    return out


def tile_cross_spectrum(field: np.ndarray, origins: list[tuple[int, int]], tile: int) -> np.ndarray:
    """Sum over tiles of the windowed cross-periodograms of an (H, W, C) field: (C, C, tile, tile) complex128.

    Each tile has its mean removed and is multiplied by :func:`hann2d`; its
    periodogram ``X_c conj(X_d) / sum(w^2)`` is a PSD in the module's
    normalisation (grid mean = variance).  Divide the sum by ``len(origins)``
    for the average (Welch's method with 2-D tiles).
    """
    f = np.asarray(field, np.float64)
    c = f.shape[2]
    out = np.zeros((c, c, tile, tile), np.complex128)
    if not origins:
        return out
    win = hann2d(tile)
    norm = float((win ** 2).sum())
    for start in range(0, len(origins), 64):
        chunk = origins[start:start + 64]
        t = np.stack([f[y:y + tile, x:x + tile] for y, x in chunk])          # (k, T, T, C)
        t = t - t.mean(axis=(1, 2), keepdims=True)
        spec = np.fft.fft2(t * win[None, :, :, None], axes=(1, 2))           # (k, T, T, C)
        out += np.einsum("kyxc,kyxd->cdyx", spec, spec.conj()) / norm
    return out


def periodogram(field: np.ndarray) -> np.ndarray:
    """Per-channel PSD of a whole (H, W[, C]) field, no window: (C, H, W), grid mean = mean square.

    Right for fields that are periodic by construction (synthesised noise);
    for camera frames use :func:`tile_cross_spectrum`.
    """
    f = np.asarray(field, np.float64)
    if f.ndim == 2:
        f = f[..., None]
    h, w = f.shape[:2]
    spec = np.fft.fft2(np.moveaxis(f, -1, 0), axes=(1, 2))
    return (spec.real ** 2 + spec.imag ** 2) / (h * w)


def _axis_weights(n_out: int, n_in: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Periodic linear-interpolation indices/weights from an n_in FFT grid to an n_out FFT grid."""
    f = np.fft.fftfreq(n_out)
    u = np.mod(f * n_in, n_in)
    i0 = np.floor(u).astype(np.int64)
    a = u - i0
    return i0 % n_in, (i0 + 1) % n_in, a


def resample_spectrum(spec: np.ndarray, shape: tuple[int, int], rfft: bool = False) -> np.ndarray:
    """Resample (..., n, m) spectra in FFT order to the FFT grid of ``shape`` = (H, W).

    Periodic bilinear interpolation in frequency (so ``S(-f) = conj(S(f))``
    is kept), then the diagonal is rescaled so that each channel's grid mean
    (its variance) equals the input's: for a (C, C, n, m) cross-spectral
    matrix the scaling is ``D S D`` with ``D = diag(sqrt(ratio))``, which
    keeps the matrix positive semi-definite and the channel correlation.
    With ``rfft=True`` only the ``W // 2 + 1`` non-negative ``fx`` columns
    (``np.fft.rfft2`` layout) are returned; the mean is still that of the full grid.
    """
    s = np.asarray(spec)
    n, m = s.shape[-2:]
    h, w = int(shape[0]), int(shape[1])
    y0, y1, ay = _axis_weights(h, n)
    x0, x1, ax = _axis_weights(w, m)
    rows = (1 - ay)[:, None] * s[..., y0, :] + ay[:, None] * s[..., y1, :]                 # (..., h, m)
    out = (1 - ax) * rows[..., :, x0] + ax * rows[..., :, x1]                             # (..., h, w)
    # keep the variance: compare grid means of the (real) diagonal PSDs
    if s.ndim >= 4 and s.shape[-4] == s.shape[-3]:
        c = s.shape[-3]
        target = np.stack([s[..., i, i, :, :].real.mean(axis=(-2, -1)) for i in range(c)], -1)
        got = np.stack([out[..., i, i, :, :].real.mean(axis=(-2, -1)) for i in range(c)], -1)
        d = np.sqrt(np.divide(target, got, out=np.ones_like(target), where=got > 0))
        out = out * d[..., :, None, None, None] * d[..., None, :, None, None]
    else:
        target = s.real.mean(axis=(-2, -1), keepdims=True)
        got = out.real.mean(axis=(-2, -1), keepdims=True)
        out = out * np.divide(target, got, out=np.ones_like(target), where=got > 0)
    if rfft:
        out = out[..., : w // 2 + 1]
    return out


def radial_average(psd: np.ndarray, bins: int = RADIAL_BINS) -> tuple[np.ndarray, np.ndarray]:
    """Radially averaged PSD of (..., H, W) spectra in FFT order.

    Returns (bin centres in cycles/pixel, (..., bins) averages) for ``bins``
    equal-width annuli covering ``0 < |f| <= 0.5``; the DC bin and the
    corners beyond the Nyquist circle are excluded.  Frequencies are
    normalised per axis, so grids of different sizes share the bins.
    """
    p = np.asarray(psd)
    h, w = p.shape[-2:]
    r = np.hypot(*np.meshgrid(np.fft.fftfreq(h), np.fft.fftfreq(w), indexing="ij"))
    edges = np.linspace(0.0, 0.5, bins + 1)
    idx = np.digitize(r, edges, right=True) - 1                  # r in (e_i, e_i+1] -> i; r = 0 -> -1
    keep = (r > 0) & (r <= 0.5)
    flat = p.reshape(-1, h * w)[:, keep.ravel()]
    ids = idx[keep]
    counts = np.bincount(ids, minlength=bins).astype(np.float64)
    sums = np.stack([np.bincount(ids, weights=row, minlength=bins) for row in flat.real])
    avg = sums / np.maximum(counts, 1)
    avg[:, counts == 0] = np.nan
    return 0.5 * (edges[:-1] + edges[1:]), avg.reshape(*p.shape[:-2], bins)


def log_spectral_distance(a: np.ndarray, b: np.ndarray) -> float:
    """RMS of ``10 log10(a / b)`` over the entries where both are finite and positive (dB); see module doc."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    if not ok.any():
        return float("nan")
    d = 10.0 * np.log10(a[ok] / b[ok])
    return float(np.sqrt(np.mean(d ** 2)))


def radial_lsd(psd_a: np.ndarray, psd_b: np.ndarray, bins: int = RADIAL_BINS) -> float:
    """LSD (dB) between the radial averages of two (..., H, W) PSDs (grids may differ in size)."""
    return log_spectral_distance(radial_average(psd_a, bins)[1], radial_average(psd_b, bins)[1])
