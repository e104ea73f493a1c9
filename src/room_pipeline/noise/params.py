"""The ``noise`` config section and the per-frame seed rule of the noise stage (domain, no I/O).

Seeds: frame ``NNNN`` of sequence ``S`` draws its noise from
``numpy.random.SeedSequence([seed, H(S), NNNN])`` with ``H(S)`` the first 4 bytes
of ``sha256(S)`` (little-endian).  :mod:`room_pipeline.stages.noise` and
``room calibrate-noise`` (:mod:`.cli`) both read the section through :class:`NoiseParams`.
"""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError
from .calibrate import CalibrationParams

#: project root (profile paths in the config are relative to it when not found from the working directory)
PROJECT_ROOT = Path(__file__).resolve().parents[3]


@dataclasses.dataclass(frozen=True)
class NoiseParams:
    """Keys of ``conf/noise/default.yaml`` (see its comments for units)."""

    profile: str = "data/noise_profiles/brea_depth_ascope4.npz"
    beta: float = 1.0
    seed: int = 0
    calibration: Any = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "NoiseParams":
        p = params_from_dict(cls, d, "noise")
        if not np.isfinite(p.beta) or p.beta < 0:
            raise ConfigError(f"noise.beta must be finite and >= 0, got {p.beta}")
        if p.seed < 0:
            raise ConfigError(f"noise.seed must be >= 0, got {p.seed}")
        if not p.profile:
            raise ConfigError("noise.profile: path of a noise profile (.npz) required")
        if p.calibration is not None and not isinstance(p.calibration, Mapping):
            raise ConfigError("noise.calibration must be a mapping of calibration keys")
        p.calibration_params()          # validate the calibration keys early
        return p

    def calibration_params(self) -> CalibrationParams:
        return params_from_dict(CalibrationParams, dict(self.calibration or {}), "noise.calibration")

    def profile_path(self) -> Path:
        """The profile file: absolute, or relative to the working directory, else to the project root."""
        return resolve_profile(self.profile)


def resolve_profile(path: str | Path) -> Path:
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    alt = PROJECT_ROOT / p
    return alt if alt.exists() else p


def sequence_hash(sequence: str) -> int:
    """Stable 32-bit hash of a sequence name (sha256, first 4 bytes little-endian); never Python's hash()."""
    return int.from_bytes(hashlib.sha256(sequence.encode("utf-8")).digest()[:4], "little")


def frame_seed(seed: int, sequence: str, index: int) -> np.random.SeedSequence:
    """The seed of frame ``index`` of ``sequence`` (see the module docstring)."""
    return np.random.SeedSequence([int(seed), sequence_hash(sequence), int(index)])
