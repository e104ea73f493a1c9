"""Noise every clean frame of a sequence, the frames shared among the executor's workers (the noise stage's
domain code).

Each frame is independent: its noise is drawn from its own seed (:func:`~room_pipeline.noise.params.frame_seed`),
so the bytes of every ``rgb_noisy`` frame, and the statistics returned in frame order, are the same with any
backend or worker count (``tests/test_noise.py``).  A worker loads the profile once and builds the
filter table once per frame size; it reads a PNG, adds the noise and writes the PNG atomically, and only a few
numbers per frame come back.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import InputError


@dataclasses.dataclass(frozen=True)
class FrameJob:
    """One frame: the clean PNG ``src``, the noisy PNG ``dst``, its frame index (the seed's third word)."""

    src: Path
    dst: Path
    index: int


class _Noiser:
    """A worker's state: the profile (loaded once) and the parameters every frame shares."""

    def __init__(self, profile_file: str, beta: float, seed: int, sequence: str) -> None:
        from .profile import NoiseProfile

        self.profile = NoiseProfile.load(profile_file)
        self.beta, self.seed, self.sequence = float(beta), int(seed), str(sequence)


def _noise_frame(state: _Noiser, job: FrameJob) -> dict:
    from ..io.images import read_png, write_png8
    from .params import frame_seed
    from .synthesize import add_noise, filter_table

    clean = read_png(job.src)
    if clean.dtype != np.uint8 or clean.ndim != 3 or clean.shape[2] != 3:
        raise InputError(f"{job.src}: expected an 8-bit RGB render, got {clean.dtype} {clean.shape}")
    ss = frame_seed(state.seed, state.sequence, job.index)
    t0 = time.perf_counter()
    filter_table(state.profile, clean.shape[:2])          # built once per frame size and worker, cached
    t1 = time.perf_counter()
    noisy = add_noise(clean, state.profile, state.beta, ss)
    t2 = time.perf_counter()
    write_png8(job.dst, noisy)
    diff = noisy.astype(np.int16) - clean.astype(np.int16)
    return {"file": job.dst.name, "index": job.index, "seed_entropy": [int(v) for v in ss.entropy],
            "added_std_levels": float(diff.std()),
            "clipped_value_fraction": float(np.mean((noisy == 0) | (noisy == 255))),
            "table_s": t1 - t0, "synthesis_s": t2 - t1}


def noise_frames(jobs: list[FrameJob], profile_file: str | Path, beta: float, seed: int, sequence: str,
                 execution: Mapping[str, Any] | None = None) -> list[dict]:
    """Noise every frame of ``jobs`` on the executor of ``execution`` (conf/execution; ``workers: 0``: one per
    core, at most one per 32 frames); one dict per frame, in the order of ``jobs``: ``file``, ``index``,
    ``seed_entropy``, ``added_std_levels`` (std of noisy - clean, 8-bit levels), ``clipped_value_fraction``
    (values at 0 or 255), ``table_s`` and ``synthesis_s`` (seconds, timing only)."""
    from ..execution import make_executor, params_for_items

    params = params_for_items(execution, len(jobs))
    with make_executor(params, init=(_Noiser, (str(profile_file), beta, seed, sequence))) as ex:
        return ex.map(_noise_frame, jobs, desc="noise")
