"""Stage `noise`: a sequence's clean renders -> the same frames with calibrated bronchoscope sensor noise.

Reads ``<patient>/<sequence>/rgb/frame_NNNN.png`` (8-bit sRGB, from `render`)
and the noise profile (``noise.profile``, a ``.npz`` with its ``.json``; see
:mod:`room_pipeline.noise.profile`).  Writes

- ``rgb_noisy/frame_NNNN.png``: ``clip(round(rgb + beta * g(luma) * n), 0, 255)``
  (:func:`room_pipeline.noise.synthesize.add_noise`); the clean ``rgb/`` is untouched;
- ``metadata/noise.json``: the profile (path, sha256, summary and provenance),
  ``beta``, the seed rule and every frame's seed, the conventions.

Seeds: frame ``NNNN`` of sequence ``S`` draws its noise from
``numpy.random.SeedSequence([seed, H(S), NNNN])`` with ``H(S)`` the first 4 bytes
of ``sha256(S)`` (little-endian) -- the same bytes on every machine and run,
different noise in every frame and sequence.
"""
from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from omegaconf import DictConfig

from ..catalog import FOLDERS, RGB_NOISY, split_key
from ..config.compose import section
from ..config.params import params_from_dict
from ..conventions import metadata_block
from ..errors import ConfigError, InputError
from ..io.atomic import write_json
from ..io.images import read_png, write_png8
from ..noise.calibrate import CalibrationParams
from ..noise.profile import NoiseProfile
from ..noise.synthesize import add_noise, filter_table
from .common import StageTimer, file_sha256, metadata, patient_paths, write_metrics

#: project root (profile paths in the config are relative to it when not found from the working directory)
PROJECT_ROOT = Path(__file__).resolve().parents[3]
IN_FOLDER = FOLDERS["rgb"]
OUT_FOLDER = FOLDERS[RGB_NOISY]


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


def frame_index(path: Path) -> int:
    try:
        return int(path.stem.split("_")[-1])
    except ValueError:
        raise InputError(f"{path}: expected a frame_NNNN.png name") from None


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    seq = patient_paths(cfg, patient).seq(sequence)
    return [seq.rgb_noisy, seq.noise_json]


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = NoiseParams.from_dict(section(cfg, "noise"))
    paths = patient_paths(cfg, patient)
    seq = paths.seq(sequence)
    src_dir, out_dir = seq.folder("rgb"), seq.rgb_noisy
    frames = sorted(src_dir.glob("frame_*.png")) if src_dir.is_dir() else []
    if not frames:
        raise InputError(f"{src_dir}: no rendered frames (frame_NNNN.png); run the render stage with rgb")
    profile_file = p.profile_path()
    profile = NoiseProfile.load(profile_file)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = {f.name for f in frames}
    for stale in out_dir.glob("frame_*.png"):
        if stale.name not in names:
            stale.unlink()
    records, added_std, clipped, synth_s, table_s = [], [], [], 0.0, 0.0
    with StageTimer() as timer:
        for f in frames:
            idx = frame_index(f)
            clean = read_png(f)
            if clean.dtype != np.uint8 or clean.ndim != 3 or clean.shape[2] != 3:
                raise InputError(f"{f}: expected an 8-bit RGB render, got {clean.dtype} {clean.shape}")
            ss = frame_seed(p.seed, sequence, idx)
            t0 = time.perf_counter()
            filter_table(profile, clean.shape[:2])          # built once per frame size, cached
            table_s += time.perf_counter() - t0
            t0 = time.perf_counter()
            noisy = add_noise(clean, profile, p.beta, ss)
            synth_s += time.perf_counter() - t0
            write_png8(out_dir / f.name, noisy)
            diff = noisy.astype(np.int16) - clean.astype(np.int16)
            added_std.append(float(diff.std()))
            clipped.append(float(np.mean((noisy == 0) | (noisy == 255))))
            records.append({"file": f.name, "index": idx, "seed_entropy": [int(v) for v in ss.entropy],
                            "added_std_levels": round(added_std[-1], 6)})
    write_json(seq.noise_json, {
        "input": f"{IN_FOLDER}/frame_NNNN.png (clean renders, kept)",
        "output": f"{OUT_FOLDER}/frame_NNNN.png = clip(round(rgb + beta * g(luma) * n), 0, 255), uint8 sRGB",
        "beta": p.beta, "seed": p.seed,
        "seed_rule": "numpy.random.SeedSequence([seed, int.from_bytes(sha256(sequence)[:4], 'little'), frame "
                     "index]) -> PCG64",
        "sequence_hash": sequence_hash(sequence),
        "profile": {"path": p.profile, "sha256": file_sha256(profile_file), "summary": profile.summary()},
        "frames": records,
        "conventions": metadata_block(),
        "metadata": metadata("noise", patient, cfg, ("noise",), sequence=sequence)})
    metrics = {"frames": len(frames), "beta": p.beta,
               "added_std_levels_mean": round(float(np.mean(added_std)), 6),
               "clipped_value_fraction_mean": round(float(np.mean(clipped)), 6),
               "synthesis_ms_per_frame": round(1e3 * synth_s / len(frames), 3),
               "filter_table_s": round(table_s, 3),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, f"noise_{sequence}", metrics)
    return metrics
