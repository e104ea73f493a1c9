"""The noise profile: what calibration measures on real frames and synthesis reproduces.

A profile is a pair of files written atomically side by side:

``<name>.npz``
    ``spectrum``      complex64 (C, C, T, T): cross-spectral matrix of the
                      sensor-output noise used for synthesis, on the T x T
                      normalised frequency grid in FFT order (see
                      :mod:`room_pipeline.noise.spectrum` for the grid and the
                      normalisation: grid mean of ``spectrum[c, c]`` = variance
                      of channel c in 8-bit levels^2);
    ``residual_psd``  float32 (C, T, T): the per-channel PSD of the bilateral
                      residual ``I - BF(I)`` measured on the calibration
                      frames (what a re-calibration of noisy frames should
                      find again);
    ``intensity_levels``, ``intensity_gain`` (only when signal-dependent noise
                      was found and modelled): float32 (K,), the noise
                      standard deviation multiplier at these 8-bit luma levels
                      (linear interpolation, held constant outside).
``<name>.json``
    Format version, channel names, grid, units and normalisation, the derived
    per-channel standard deviation and correlation matrix, the intensity
    dependence test, provenance (source folder, frames used and held out,
    filter parameters, code version) and the sha256 of the ``.npz``.

The ``.npz`` bytes are deterministic (fixed zip timestamps), so a re-run of
the same calibration gives the same files.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.atomic import write_json, write_with

FORMAT = "room-noise-profile/1"
CHANNELS = ("R", "G", "B")
UNITS = {"intensity": "8-bit sRGB levels (0..255) of the sensor output",
         "frequency": "cycles/pixel, each axis in [-0.5, 0.5), FFT order",
         "spectrum": "levels^2 per (cycle/pixel)^2; grid mean of spectrum[c, c] = variance of channel c"}


@dataclasses.dataclass(frozen=True)
class IntensityModel:
    """Signal-dependent noise: standard-deviation gain as a function of the clean image's luma (8-bit)."""

    levels: np.ndarray
    gain: np.ndarray

    def __post_init__(self) -> None:
        lv, g = np.asarray(self.levels, np.float64), np.asarray(self.gain, np.float64)
        if lv.ndim != 1 or lv.shape != g.shape or len(lv) < 2 or np.any(np.diff(lv) <= 0) \
                or not np.all(np.isfinite(g)) or np.any(g < 0):
            raise InputError("intensity model: levels must increase and gains be finite and >= 0 (same length >= 2)")

    def gain_at(self, luma: np.ndarray) -> np.ndarray:
        """Gain at each luma value (float32, same shape), piecewise linear, constant outside the levels."""
        return np.interp(luma, self.levels, self.gain).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class NoiseProfile:
    """Measured noise statistics of a camera's output frames (see the module docstring for the arrays).

    Compared and hashed by identity (synthesis caches its filter tables per profile object).
    """

    spectrum: np.ndarray
    residual_psd: np.ndarray
    intensity: IntensityModel | None = None
    intensity_test: dict = dataclasses.field(default_factory=dict)
    provenance: dict = dataclasses.field(default_factory=dict)
    channels: tuple = CHANNELS

    def __post_init__(self) -> None:
        s = np.asarray(self.spectrum)
        if s.ndim != 4 or s.shape[0] != s.shape[1] or s.shape[2] != s.shape[3] or s.shape[2] < 4:
            raise InputError(f"noise profile: spectrum must be (C, C, T, T) with T >= 4, got {s.shape}")
        if np.asarray(self.residual_psd).shape != (s.shape[0], s.shape[2], s.shape[3]):
            raise InputError(f"noise profile: residual_psd must be {(s.shape[0],) + s.shape[2:]}, "
                             f"got {np.asarray(self.residual_psd).shape}")
        if len(self.channels) != s.shape[0]:
            raise InputError(f"noise profile: {s.shape[0]} channels but names {self.channels}")
        if not np.all(np.isfinite(s)):
            raise InputError("noise profile: spectrum has non-finite values")

    # ------------------------------------------------------------------ derived quantities

    @property
    def tile(self) -> int:
        """Size T of the frequency grid (the calibration tile, pixels)."""
        return int(np.asarray(self.spectrum).shape[-1])

    @property
    def psd(self) -> np.ndarray:
        """(C, T, T) per-channel PSDs (the real diagonal of the cross-spectral matrix)."""
        s = np.asarray(self.spectrum)
        return np.stack([s[i, i].real for i in range(s.shape[0])]).astype(np.float64)

    @property
    def covariance(self) -> np.ndarray:
        """(C, C) zero-lag channel covariance, levels^2 (grid mean of the cross-spectral matrix)."""
        return np.asarray(self.spectrum).mean(axis=(-2, -1)).real.astype(np.float64)

    @property
    def std(self) -> np.ndarray:
        """(C,) per-channel noise standard deviation, 8-bit levels (before any intensity gain)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    @property
    def correlation(self) -> np.ndarray:
        """(C, C) zero-lag channel correlation matrix."""
        cov = self.covariance
        d = np.sqrt(np.clip(np.diag(cov), 1e-30, None))
        return cov / np.outer(d, d)

    def summary(self) -> dict:
        """JSON-ready description (no large arrays)."""
        return {"format": FORMAT, "channels": list(self.channels), "grid": self.tile,
                "units": UNITS,
                "std_levels": [round(float(v), 6) for v in self.std],
                "correlation": np.round(self.correlation, 6).tolist(),
                "residual_std_levels": [round(float(v), 6)
                                        for v in np.sqrt(np.asarray(self.residual_psd).mean(axis=(-2, -1)))],
                "intensity_model": None if self.intensity is None else {
                    "luma_levels": np.round(self.intensity.levels, 4).tolist(),
                    "std_gain": np.round(self.intensity.gain, 6).tolist(),
                    "meaning": "noise std multiplier vs the clean image's Rec.601 luma (8-bit), linear interpolation"},
                "intensity_test": finite(self.intensity_test), "provenance": finite(self.provenance)}

    # ------------------------------------------------------------------ files

    def save(self, path: str | Path) -> tuple[Path, Path]:
        """Write ``path`` (.npz) and the ``.json`` next to it, atomically; returns both paths."""
        path = Path(path)
        if path.suffix != ".npz":
            raise InputError(f"noise profile path must end in .npz: {path}")
        arrays = {"spectrum": np.asarray(self.spectrum).astype(np.complex64),
                  "residual_psd": np.asarray(self.residual_psd).astype(np.float32)}
        if self.intensity is not None:
            arrays["intensity_levels"] = np.asarray(self.intensity.levels, np.float32)
            arrays["intensity_gain"] = np.asarray(self.intensity.gain, np.float32)
        data = npz_bytes(arrays)
        write_with(path, lambda tmp: tmp.write_bytes(data))
        meta = self.summary()
        meta["npz"] = {"file": path.name, "sha256": hashlib.sha256(data).hexdigest(),
                       "arrays": {k: [str(v.dtype), list(v.shape)] for k, v in arrays.items()}}
        json_path = path.with_suffix(".json")
        write_json(json_path, meta)
        return path, json_path

    @classmethod
    def load(cls, path: str | Path) -> "NoiseProfile":
        """Read a profile written by :meth:`save` (the ``.json`` must sit next to the ``.npz``)."""
        path = Path(path)
        json_path = path.with_suffix(".json")
        if not path.is_file():
            raise InputError(f"noise profile not found: {path}")
        if not json_path.is_file():
            raise InputError(f"noise profile metadata not found: {json_path}")
        try:
            meta = json.loads(json_path.read_text(encoding="utf-8"))
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise InputError(f"{path}: not a readable noise profile ({exc})") from None
        if meta.get("format") != FORMAT:
            raise InputError(f"{json_path}: format {meta.get('format')!r}, expected {FORMAT!r}")
        missing = {"spectrum", "residual_psd"} - set(arrays)
        if missing:
            raise InputError(f"{path}: missing arrays {sorted(missing)}")
        intensity = None
        if "intensity_levels" in arrays:
            intensity = IntensityModel(arrays["intensity_levels"].astype(np.float64),
                                       arrays["intensity_gain"].astype(np.float64))
        return cls(spectrum=arrays["spectrum"].astype(np.complex128),
                   residual_psd=arrays["residual_psd"].astype(np.float64), intensity=intensity,
                   intensity_test=meta.get("intensity_test", {}), provenance=meta.get("provenance", {}),
                   channels=tuple(meta.get("channels", CHANNELS)))


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A compressed ``.npz`` (readable by ``np.load``) with fixed zip timestamps: deterministic bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def finite(obj: Any) -> Any:
    """Nested dicts/lists with numpy scalars as Python numbers and NaN/inf as None (JSON has no such numbers)."""
    if isinstance(obj, dict):
        return {str(k): finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [finite(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
