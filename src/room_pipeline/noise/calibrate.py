"""Noise calibration: real endoscope frames -> :class:`~room_pipeline.noise.profile.NoiseProfile`.

Per frame (8-bit RGB, intensities in levels 0..255):

1. valid pixels: every channel below ``saturation_level`` (no clipped
   specular highlights) and some channel above ``dark_level`` (no black
   vignetting, borders or unlit lumen), eroded by ``mask_margin_px`` so the
   bilateral filter never reaches across the boundary of an excluded region;
2. residual ``n = I - BF(I)``: OpenCV's bilateral filter on the float RGB
   frame (joint colour distance; ``bilateral_d`` pixels,
   ``bilateral_sigma_color`` levels, ``bilateral_sigma_space`` pixels);
3. cross-spectral matrix of ``n`` by 2-D Welch averaging: ``tile x tile``
   windows on a ``tile_step`` grid that lie entirely in the valid mask, mean
   removed, Hann-windowed, periodogram normalised by the window energy so
   the PSD is per unit frequency area (grid mean = variance; see
   :mod:`~room_pipeline.noise.spectrum`).  Tiles of frames of any size share
   the fixed ``tile x tile`` normalised frequency grid, so frames of
   different sizes average bin by bin;
4. intensity dependence: the residual variance in luma bins of ``BF(I)``
   (valid pixels), fitted per frame by ``var = a + b * Y`` (the
   Poisson-Gaussian sensor model); the slope ``b`` is tested across frames
   (one-sample t-test, frames as replicates).  It is modelled only when
   significant (``p < intensity_alpha``) *and* large (the noise standard
   deviation changes by more than ``intensity_min_change`` between the 10th and
   90th luma percentiles of the calibration pixels); then the profile carries
   a gain table ``sqrt((a + b Y) / mean var)``.

Filter compensation (``compensate_filter``)
    The residual is not the noise: ``BF`` also removes part of the noise (the
    residual operator attenuates low frequencies strongly, the noise at high
    frequencies hardly), so noise synthesised with the residual spectrum and
    re-calibrated would come back attenuated a second time.  The synthesis
    spectrum ``S`` is therefore the fixed point of
    ``residual_spectrum(BF(I) + noise(S)) = measured residual spectrum``:
    starting from ``S = measured``, noise is synthesised on the filtered
    calibration frames (quantised to 8 bits like the real output), the
    residual spectrum re-measured on the same tiles, and every bin of ``S``
    scaled by the ratio (``D S D`` with ``D = sqrt(measured / re-measured)``
    per channel, at most ``max_compensation_db``; correlation kept).  Below
    the filter's cut-off the residual carries little of the noise, so the
    estimate there is the least certain; the cap bounds it.

JPEG input
    The test frames are JPEGs (4:2:0 chroma subsampling, 8x8 DCT blocks): the
    measured spectrum is that of the camera *output*, compression included --
    high frequencies attenuated by DCT quantisation, any 8x8 block-grid
    structure at multiples of 1/8 cycle/pixel (weak in the BREA-Depth frames,
    see ``benchmarks/results/noise.md``), chroma noise band-limited and
    strongly correlated across R, G, B.  The profile reproduces this output,
    not the raw sensor noise.
"""
from __future__ import annotations

import dataclasses
import hashlib
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .. import __version__
from ..config.params import params_from_dict
from ..errors import ConfigError, InputError
from .profile import IntensityModel, NoiseProfile
from .spectrum import tile_cross_spectrum, tile_origins


@dataclasses.dataclass(frozen=True)
class CalibrationParams:
    """Calibration settings (the calibration keys of ``conf/noise/default.yaml``; units there)."""

    bilateral_d: int = 9
    bilateral_sigma_color: float = 20.0
    bilateral_sigma_space: float = 3.0
    tile: int = 64
    tile_step: int = 32
    dark_level: float = 10.0
    saturation_level: float = 250.0
    mask_margin_px: int = 6
    holdout_every: int = 4
    holdout_offset: int = 3
    intensity_bins: int = 12
    intensity_min_pixels: int = 500
    intensity_alpha: float = 0.01
    intensity_min_change: float = 0.2
    compensate_filter: bool = True
    compensation_iterations: int = 5
    compensation_frames: int = 12
    max_compensation_db: float = 20.0
    compensation_blur_px: float = 8.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.bilateral_d < 1 or self.bilateral_sigma_color <= 0 or self.bilateral_sigma_space <= 0:
            raise ConfigError("noise: bilateral_d >= 1 and bilateral sigmas > 0 required")
        if self.tile < 8 or self.tile % 2 or not 1 <= self.tile_step <= self.tile:
            raise ConfigError(f"noise: tile must be even and >= 8 and 1 <= tile_step <= tile "
                              f"(got {self.tile}, {self.tile_step})")
        if not 0 <= self.dark_level < self.saturation_level <= 256:
            raise ConfigError("noise: 0 <= dark_level < saturation_level <= 256 required")
        if self.mask_margin_px < 0 or self.holdout_every < 0 or self.holdout_offset < 0:
            raise ConfigError("noise: mask_margin_px, holdout_every and holdout_offset must be >= 0")
        if self.holdout_every == 1 or (self.holdout_every and self.holdout_offset >= self.holdout_every):
            raise ConfigError("noise: holdout_every must be 0 (no hold-out) or >= 2, "
                              "and holdout_offset < holdout_every")
        if self.intensity_bins < 3 or not 0 < self.intensity_alpha < 1 or self.intensity_min_change < 0:
            raise ConfigError("noise: intensity_bins >= 3, 0 < intensity_alpha < 1, intensity_min_change >= 0")
        if self.compensation_iterations < 0 or self.compensation_frames < 1 or self.max_compensation_db < 0:
            raise ConfigError("noise: compensation_iterations >= 0, compensation_frames >= 1, "
                              "max_compensation_db >= 0 required")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "CalibrationParams":
        return params_from_dict(cls, d, "noise")

    def filter_dict(self) -> dict:
        return {"bilateral_d_px": self.bilateral_d, "bilateral_sigma_color_levels": self.bilateral_sigma_color,
                "bilateral_sigma_space_px": self.bilateral_sigma_space,
                "implementation": "cv2.bilateralFilter on float32 RGB (joint colour distance), BORDER_REFLECT_101"}


# --------------------------------------------------------------------------- per-frame measurements


def valid_mask(image_u8: np.ndarray, p: CalibrationParams) -> np.ndarray:
    """(H, W) bool: pixels neither dark nor saturated, eroded by ``mask_margin_px``."""
    import cv2

    img = np.asarray(image_u8)
    ok = (img.max(axis=2) > p.dark_level) & (img.max(axis=2) < p.saturation_level)
    if p.mask_margin_px > 0 and ok.any() and not ok.all():
        k = 2 * p.mask_margin_px + 1
        ok = cv2.erode(ok.astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
    return ok


def bilateral(image: np.ndarray, p: CalibrationParams) -> np.ndarray:
    """Bilateral-filtered float32 copy of an (H, W, 3) image (levels)."""
    import cv2

    src = np.ascontiguousarray(image, dtype=np.float32)
    return cv2.bilateralFilter(src, p.bilateral_d, p.bilateral_sigma_color, p.bilateral_sigma_space)


def residual(image: np.ndarray, p: CalibrationParams) -> tuple[np.ndarray, np.ndarray]:
    """(noise residual ``I - BF(I)``, ``BF(I)``), both float32 (H, W, 3) in levels."""
    smooth = bilateral(image, p)
    return np.asarray(image, np.float32) - smooth, smooth


def texture_free(image: np.ndarray, p: CalibrationParams) -> np.ndarray:
    """The frame's shading without texture or noise: Gaussian blur of ``compensation_blur_px`` (float32)."""
    import cv2

    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), p.compensation_blur_px)


def luma(image: np.ndarray) -> np.ndarray:
    """Rec.601 luma of an (H, W, 3) RGB image (same units), float32."""
    return (np.asarray(image, np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.float32)


@dataclasses.dataclass
class FrameStats:
    """What one frame contributes: summed tile cross-spectra and per-luma-bin residual power."""

    name: str
    shape: tuple[int, int]
    spectrum_sum: np.ndarray         # (C, C, T, T) complex, sum over tiles
    tiles: int
    bin_count: np.ndarray            # (K,) valid pixels per luma bin
    bin_power: np.ndarray            # (K,) summed mean-over-channels residual^2 per luma bin
    valid_fraction: float


def luma_edges(p: CalibrationParams) -> np.ndarray:
    """Luma bin edges (8-bit levels) of the intensity-dependence test."""
    return np.linspace(p.dark_level, p.saturation_level, p.intensity_bins + 1)


def frame_stats(image_u8: np.ndarray, p: CalibrationParams, name: str = "") -> tuple[FrameStats, np.ndarray,
                                                                                       list]:
    """Measure one frame; returns (stats, BF(I), tile origins)."""
    img = np.asarray(image_u8)
    mask = valid_mask(img, p)
    resid, smooth = residual(img, p)
    origins = tile_origins(mask, p.tile, p.tile_step)
    spec = tile_cross_spectrum(resid, origins, p.tile)
    y = luma(smooth)[mask]
    power = (resid[mask].astype(np.float64) ** 2).mean(axis=1)
    edges = luma_edges(p)
    idx = np.clip(np.digitize(y, edges) - 1, 0, p.intensity_bins - 1)
    count = np.bincount(idx, minlength=p.intensity_bins).astype(np.float64)
    psum = np.bincount(idx, weights=power, minlength=p.intensity_bins)
    stats = FrameStats(name, tuple(img.shape[:2]), spec, len(origins), count, psum, float(mask.mean()))
    return stats, smooth, origins


# --------------------------------------------------------------------------- intensity dependence


def intensity_dependence(stats: Sequence[FrameStats], p: CalibrationParams) -> tuple[dict, IntensityModel | None]:
    """Test whether the residual variance grows (or falls) with intensity; fit the model if it matters.

    Returns (a JSON-ready report, the model or None).  See the module docstring.
    """
    from scipy import stats as sst

    edges = luma_edges(p)
    centres = 0.5 * (edges[:-1] + edges[1:])
    counts = np.stack([s.bin_count for s in stats])
    powers = np.stack([s.bin_power for s in stats])
    pooled_n = counts.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled_var = np.where(pooled_n > 0, powers.sum(0) / np.maximum(pooled_n, 1), np.nan)
    slopes, intercepts = [], []
    for n, pw in zip(counts, powers):
        use = n >= p.intensity_min_pixels
        if use.sum() < 3:
            continue
        v = pw[use] / n[use]
        b, a = np.polyfit(centres[use], v, 1, w=np.sqrt(n[use]))
        slopes.append(b)
        intercepts.append(a)
    report: dict = {"luma_bin_centres": np.round(centres, 3).tolist(),
                    "pooled_pixels": pooled_n.astype(int).tolist(),
                    "pooled_residual_var": [None if not np.isfinite(v) else round(float(v), 6) for v in pooled_var],
                    "frames_tested": len(slopes), "model": "var = a + b * luma (per frame, weighted LS)",
                    "alpha": p.intensity_alpha, "min_change": p.intensity_min_change}
    use = pooled_n >= p.intensity_min_pixels
    if use.sum() >= 3:
        b_pool, a_pool = np.polyfit(centres[use], pooled_var[use], 1, w=np.sqrt(pooled_n[use]))
        report.update(pooled_slope=float(b_pool), pooled_intercept=float(a_pool))
    if len(slopes) < 3:
        report.update(significant=False, modelled=False,
                      decision=f"not tested: {len(slopes)} frame(s) with >= 3 populated luma bins (need 3)")
        return report, None
    s = np.asarray(slopes)
    mean_b = float(s.mean())
    se = float(s.std(ddof=1) / np.sqrt(len(s)))
    t = mean_b / se if se > 0 else (np.inf if mean_b != 0 else 0.0)
    pval = float(2 * sst.t.sf(abs(t), df=len(s) - 1)) if np.isfinite(t) else 0.0
    a_mean = float(np.mean(intercepts))
    # effect size between the 10th and 90th luma percentiles of the calibration pixels
    cdf = np.cumsum(pooled_n) / max(pooled_n.sum(), 1)
    y10 = float(np.interp(0.1, cdf, edges[1:]))
    y90 = float(np.interp(0.9, cdf, edges[1:]))
    v10, v90 = a_mean + mean_b * y10, a_mean + mean_b * y90
    ratio = float(np.sqrt(v90 / v10)) if v10 > 0 and v90 > 0 else float("inf")
    significant = pval < p.intensity_alpha
    large = abs(np.log(ratio)) > np.log1p(p.intensity_min_change) if np.isfinite(ratio) else True
    report.update(slope_mean=mean_b, slope_se=se, t=float(t), p_value=pval, intercept_mean=a_mean,
                  luma_p10=y10, luma_p90=y90, std_ratio_p90_p10=ratio, significant=bool(significant),
                  modelled=bool(significant and large))
    if not (significant and large):
        why = "slope not significant" if not significant else \
            f"std changes by only {100 * (ratio - 1):+.1f}% between luma p10 and p90"
        report["decision"] = f"signal-independent noise modelled ({why})"
        return report, None
    levels = np.linspace(0.0, 255.0, 18)
    var = np.clip(a_mean + mean_b * levels, 1e-6, None)
    mean_var = float(np.sum(pooled_n * np.clip(a_mean + mean_b * centres, 1e-6, None)) / pooled_n.sum())
    report["decision"] = "signal-dependent noise modelled: std gain sqrt((a + b Y) / pixel-mean variance)"
    return report, IntensityModel(levels, np.sqrt(var / mean_var))


# --------------------------------------------------------------------------- filter compensation


def _compensate(measured: np.ndarray, frames: list[tuple[np.ndarray, list]], p: CalibrationParams,
                intensity: IntensityModel | None) -> tuple[np.ndarray, list[float]]:
    """Fixed-point synthesis spectrum whose bilateral residual matches ``measured`` (see module doc).

    Returns the spectrum and, per iteration, the RMS (dB, over bins and channels) of the remaining
    mismatch between the re-measured and the measured residual PSDs.
    """
    from .synthesize import synthesize

    c = measured.shape[0]
    diag_meas = np.stack([measured[i, i].real for i in range(c)])
    cap = 10 ** (p.max_compensation_db / 10)
    spec = measured.copy()
    history = []
    for it in range(p.compensation_iterations):
        prof = NoiseProfile(spec, diag_meas, intensity=intensity)
        acc = np.zeros_like(measured)
        n = 0
        for k, (smooth, origins) in enumerate(frames):
            rng = np.random.Generator(np.random.PCG64([p.seed, it, k]))
            noise = synthesize(prof, smooth.shape[:2], rng)
            if intensity is not None:
                noise = noise * intensity.gain_at(luma(smooth))[..., None]
            noisy = np.clip(np.rint(smooth + noise), 0, 255)
            resid, _ = residual(noisy, p)
            acc += tile_cross_spectrum(resid, origins, p.tile)
            n += len(origins)
        again = acc / n
        diag_again = np.stack([again[i, i].real for i in range(c)])
        ratio = np.divide(diag_meas, diag_again, out=np.ones_like(diag_meas), where=diag_again > 0)
        ok = (diag_meas > 0) & (diag_again > 0)
        history.append(float(np.sqrt(np.mean((10 * np.log10(ratio[ok])) ** 2))) if ok.any() else 0.0)
        diag_spec = np.stack([spec[i, i].real for i in range(c)])
        # cumulative gain relative to the measured residual, capped
        gain = np.clip(np.divide(diag_spec * ratio, diag_meas, out=np.ones_like(diag_meas),
                                 where=diag_meas > 0), 1 / cap, cap)
        new_diag = diag_meas * gain
        d = np.sqrt(np.divide(new_diag, diag_spec, out=np.ones_like(new_diag), where=diag_spec > 0))
        spec = spec * d[:, None] * d[None, :]
    return spec, history


# --------------------------------------------------------------------------- entry points


def calibrate_images(images: Sequence[np.ndarray], p: CalibrationParams, names: Sequence[str] | None = None,
                     provenance: Mapping[str, Any] | None = None) -> NoiseProfile:
    """Calibrate a profile from (H, W, 3) uint8 RGB frames (sizes may differ).

    Frames without a single valid tile (all dark, saturated, or smaller than
    the tile) are skipped with a warning; :class:`InputError` when none is left.
    """
    if len(images) == 0:
        raise InputError("noise calibration: no frames given")
    names = list(names) if names is not None else [f"frame_{i:04d}" for i in range(len(images))]
    stats: list[FrameStats] = []
    keep_every = max(1, int(np.ceil(len(images) / p.compensation_frames)))
    comp_frames: list[tuple[np.ndarray, list]] = []
    for i, (img, name) in enumerate(zip(images, names)):
        a = np.asarray(img)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
            raise InputError(f"noise calibration: {name}: need (H, W, 3) uint8 RGB, got {a.dtype} {a.shape}")
        st, smooth, origins = frame_stats(a, p, name)
        if st.tiles == 0:
            warnings.warn(f"noise calibration: {name} ({a.shape[1]}x{a.shape[0]}): no {p.tile}x{p.tile} tile of "
                          f"valid pixels (dark <= {p.dark_level:g} or saturated >= {p.saturation_level:g}); "
                          f"frame skipped", stacklevel=2)
            continue
        stats.append(st)
        if i % keep_every == 0 and len(comp_frames) < p.compensation_frames:
            comp_frames.append((texture_free(a, p), origins))
    if not stats:
        raise InputError(f"noise calibration: none of the {len(images)} frame(s) has a {p.tile}x{p.tile} tile of "
                         f"valid (not dark, not saturated) pixels")
    tiles = sum(s.tiles for s in stats)
    measured = sum(s.spectrum_sum for s in stats) / tiles
    c = measured.shape[0]
    residual_psd = np.stack([measured[i, i].real for i in range(c)])
    report, model = intensity_dependence(stats, p)
    history: list[float] = []
    spectrum = measured
    if p.compensate_filter and p.compensation_iterations > 0:
        spectrum, history = _compensate(measured, comp_frames, p, model)
    prov = dict(provenance or {})
    prov.update({
        "frames_used": [s.name for s in stats],
        "frame_count": len(stats),
        "frame_shapes": sorted({f"{s.shape[1]}x{s.shape[0]}" for s in stats}),
        "tiles": tiles, "tiles_per_frame": [s.tiles for s in stats],
        "valid_fraction_mean": round(float(np.mean([s.valid_fraction for s in stats])), 6),
        "filter": p.filter_dict(),
        "psd": {"method": "2-D Welch: Hann-windowed tiles entirely inside the valid mask, mean removed",
                "tile_px": p.tile, "tile_step_px": p.tile_step,
                "normalisation": "|DFT|^2 / sum(window^2): PSD per unit frequency area, grid mean = variance"},
        "mask": {"dark_level": p.dark_level, "saturation_level": p.saturation_level,
                 "margin_px": p.mask_margin_px,
                 "rule": "valid = max(R,G,B) > dark_level and max(R,G,B) < saturation_level, eroded by margin"},
        "filter_compensation": {"enabled": bool(p.compensate_filter and p.compensation_iterations > 0),
                                "iterations": p.compensation_iterations, "frames": len(comp_frames),
                                "max_db": p.max_compensation_db, "seed": p.seed,
                                "residual_mismatch_db_per_iteration": [round(h, 4) for h in history]},
        "room_pipeline_version": __version__,
    })
    return NoiseProfile(spectrum=spectrum, residual_psd=residual_psd, intensity=model, intensity_test=report,
                        provenance=prov)


IMAGE_HINT = "JPEG/PNG/TIFF/BMP"


def read_rgb(path: Path) -> np.ndarray | None:
    """(H, W, 3) uint8 RGB of an image file, or None when it is not a decodable image."""
    import cv2

    try:
        data = np.fromfile(str(path), np.uint8)
    except OSError:
        return None
    if data.size == 0:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        return None
    return np.ascontiguousarray(img[..., ::-1])


def list_images(folder: str | Path) -> list[tuple[Path, np.ndarray]]:
    """Decodable images of a folder (not recursive), sorted by name; other files skipped with a warning."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"noise calibration: frames folder not found: {folder}")
    out = []
    for f in sorted(x for x in folder.iterdir() if x.is_file()):
        img = read_rgb(f)
        if img is None:
            warnings.warn(f"noise calibration: skipping {f.name}: not a readable image", stacklevel=2)
            continue
        out.append((f, img))
    if not out:
        raise InputError(f"noise calibration: no readable images ({IMAGE_HINT}) in {folder}")
    return out


def split_frames(n: int, every: int, offset: int) -> tuple[list[int], list[int]]:
    """(calibration indices, held-out indices) of ``n`` frames sorted by name: index % every == offset is held out.

    ``every = 0`` holds nothing out; the calibration set is never emptied (a
    folder with fewer than ``offset + 1`` frames holds nothing out).
    """
    if every <= 0:
        return list(range(n)), []
    held = [i for i in range(n) if i % every == offset]
    calib = [i for i in range(n) if i % every != offset]
    return calib, held


def calibrate_folder(folder: str | Path, params: CalibrationParams) -> NoiseProfile:
    """Calibrate a profile from the images of ``folder`` (its hold-out split is kept out and recorded)."""
    files = list_images(folder)
    calib, held = split_frames(len(files), params.holdout_every, params.holdout_offset)

    def sha(path: Path) -> str:
        return hashlib.sha256(path.read_bytes()).hexdigest()

    prov = {"source_folder": str(folder), "files_found": len(files),
            "split": {"rule": f"frames sorted by file name; index % {params.holdout_every} == "
                              f"{params.holdout_offset} held out" if params.holdout_every else "none held out",
                      "held_out": [files[i][0].name for i in held]},
            "frame_sha256": {files[i][0].name: sha(files[i][0]) for i in calib}}
    return calibrate_images([files[i][1] for i in calib], params, names=[files[i][0].name for i in calib],
                            provenance=prov)
