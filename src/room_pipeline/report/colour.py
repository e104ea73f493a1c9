"""Colour mapping of the rendered modalities (pure NumPy): colour maps, normals, flow, labels, thumbnails."""
from __future__ import annotations

import functools

import numpy as np


@functools.lru_cache(maxsize=None)
def _lut(name: str) -> np.ndarray:
    """The 256-entry uint8 RGB table of a matplotlib colour map (read-only)."""
    import matplotlib

    lut = np.rint(matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def colorize(values: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis",
             valid: np.ndarray | None = None) -> np.ndarray:
    """Scalar image -> (H, W, 3) uint8 through a matplotlib colour map, clipped to [vmin, vmax];
    black where not ``valid``."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    t = np.clip((np.nan_to_num(v) - vmin) / span, 0.0, 1.0)
    out = _lut(cmap)[np.rint(t * 255).astype(np.int64)]
    if valid is not None:
        out[~np.asarray(valid, bool)] = 0
    return out


def normals_rgb(normals: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (camera frame) -> RGB = (n + 1) / 2 of (x, y, z); black where not valid (or n = 0)."""
    n = np.asarray(normals, dtype=np.float64)
    out = np.rint(np.clip((n + 1.0) * 0.5, 0.0, 1.0) * 255).astype(np.uint8)
    ok = np.any(n != 0, axis=-1) if valid is None else np.asarray(valid, bool)
    out[~ok] = 0
    return out


def flow_rgb(flow: np.ndarray, valid: np.ndarray | None, max_px: float) -> np.ndarray:
    """Optical flow (pixels, u along columns, v along rows) -> RGB: hue = direction, saturation =
    magnitude / ``max_px`` (clipped to 1), black where not valid.  Hue 0 (red) = +u (right)."""
    import cv2

    f = np.asarray(flow, dtype=np.float64)
    u, v = f[..., 0], f[..., 1]
    ang = np.mod(np.arctan2(v, u), 2 * np.pi)
    hsv = np.empty(u.shape + (3,), np.uint8)
    hsv[..., 0] = np.rint(ang / (2 * np.pi) * 180).astype(np.int64) % 180
    hsv[..., 1] = np.rint(np.clip(np.hypot(u, v) / max(max_px, 1e-12), 0, 1) * 255).astype(np.uint8)
    hsv[..., 2] = 255
    out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if valid is not None:
        out[~np.asarray(valid, bool)] = 0
    return out


def labels_rgb(labels: np.ndarray) -> np.ndarray:
    """Integer labels -> RGB, a fixed colour per label (golden-ratio hues), 0 (no hit) black."""
    import matplotlib.colors as mcolors

    lab = np.asarray(labels).astype(np.int64)
    ids, inv = np.unique(lab, return_inverse=True)
    hue = np.mod(ids * 0.6180339887498949, 1.0)
    sat = 0.55 + 0.35 * np.mod(ids * 0.37, 1.0)
    pal = np.rint(mcolors.hsv_to_rgb(np.stack([hue, sat, np.full_like(hue, 0.95)], -1)) * 255).astype(np.uint8)
    pal[ids == 0] = 0
    return pal[inv.reshape(lab.shape)]


def colour_bar(cmap: str, width: int = 160, height: int = 10) -> np.ndarray:
    """A horizontal colour bar (low values on the left)."""
    return colorize(np.tile(np.linspace(0, 1, width), (height, 1)), 0.0, 1.0, cmap)


def flow_wheel(size: int = 48) -> np.ndarray:
    """The flow colour key: a disc whose pixel at (u, v) from the centre has that flow's colour (radius = max)."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    f = np.stack([xx - c, yy - c], -1)
    return flow_rgb(f, np.hypot(f[..., 0], f[..., 1]) <= c, c)


def thumbnail(img: np.ndarray, px: int, nearest: bool = False) -> np.ndarray:
    """Downscale so the longer side is ``px`` (area averaging; ``nearest`` for labels); never upscales."""
    import cv2

    h, w = img.shape[:2]
    s = px / max(h, w)
    if s >= 1.0:
        return np.ascontiguousarray(img)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(img, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def pick_frames(n: int, k: int) -> list[int]:
    """``k`` evenly spaced positions in 0..n-1 (first and last included), sorted, unique."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(k, n))})
