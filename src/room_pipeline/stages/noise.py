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

from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from ..catalog import FOLDERS, RGB_NOISY, split_key
from ..config.compose import section
from ..conventions import metadata_block
from ..errors import InputError
from ..io.atomic import write_json
from ..noise.params import (PROJECT_ROOT, NoiseParams, frame_seed, resolve_profile,  # noqa: F401 (re-exported)
                             sequence_hash)
from ..noise.profile import NoiseProfile
from ..noise.sequence import FrameJob, noise_frames
from ..io.hashing import sha256_file
from .common import StageTimer, metadata, patient_paths, write_metrics, write_sequence_record

IN_FOLDER = FOLDERS["rgb"]
OUT_FOLDER = FOLDERS[RGB_NOISY]


def frame_index(path: Path) -> int:
    try:
        return int(path.stem.split("_")[-1])
    except ValueError:
        raise InputError(f"{path}: expected a frame_NNNN.png name") from None


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    seq = patient_paths(cfg, patient).seq(sequence)
    return [seq.rgb_noisy, seq.noise_json, patient_paths(cfg, patient).sequence_record(sequence, "noise")]


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
    profile = NoiseProfile.load(profile_file)            # a bad profile stops here, before any worker starts
    out_dir.mkdir(parents=True, exist_ok=True)
    names = {f.name for f in frames}
    for stale in out_dir.glob("frame_*.png"):
        if stale.name not in names:
            stale.unlink()
    jobs = [FrameJob(f, out_dir / f.name, frame_index(f)) for f in frames]
    with StageTimer() as timer:      # the frames shared among the execution workers (noise/sequence.py)
        done = noise_frames(jobs, profile_file, p.beta, p.seed, sequence, cfg.get("execution"))
    added_std = [d["added_std_levels"] for d in done]
    clipped = [d["clipped_value_fraction"] for d in done]
    synth_s, table_s = sum(d["synthesis_s"] for d in done), sum(d["table_s"] for d in done)
    records = [{"file": d["file"], "index": d["index"], "seed_entropy": d["seed_entropy"],
                "added_std_levels": round(d["added_std_levels"], 6)} for d in done]
    write_json(seq.noise_json, {
        "input": f"{IN_FOLDER}/frame_NNNN.png (clean renders, kept)",
        "output": f"{OUT_FOLDER}/frame_NNNN.png = clip(round(rgb + beta * g(luma) * n), 0, 255), uint8 sRGB",
        "beta": p.beta, "seed": p.seed,
        "seed_rule": "numpy.random.SeedSequence([seed, int.from_bytes(sha256(sequence)[:4], 'little'), frame "
                     "index]) -> PCG64",
        "sequence_hash": sequence_hash(sequence),
        "profile": {"path": p.profile, "sha256": sha256_file(profile_file), "summary": profile.summary()},
        "frames": records,
        "conventions": metadata_block(),
        "metadata": metadata("noise", patient, cfg, ("noise",), sequence=sequence)})
    metrics = {"frames": len(frames), "beta": p.beta,
               "added_std_levels_mean": round(float(np.mean(added_std)), 6),
               "clipped_value_fraction_mean": round(float(np.mean(clipped)), 6),
               "synthesis_ms_per_frame": round(1e3 * synth_s / len(frames), 3),
               "filter_table_s": round(table_s, 3),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_sequence_record(paths, sequence, "noise", {RGB_NOISY: out_dir})     # train_depth's dep (render's too)
    write_metrics(paths, "noise", metrics, sequence=sequence)
    return metrics
