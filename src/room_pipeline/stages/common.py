"""Shared plumbing of the stage modules: paths, metadata, timing, metrics."""
from __future__ import annotations

import resource
import time
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from .. import __version__
from ..conventions import metadata_block
from ..io.atomic import write_json
from ..io.hashing import sha256_file
from ..io.jsondoc import finite as _finite, read_json, round_floats  # noqa: F401 (the stages' names)
from ..io.metrics import split_timings, write_metrics_file
from ..paths import PatientPaths


def patient_paths(cfg: DictConfig, patient: str) -> PatientPaths:
    return PatientPaths(Path(cfg.output_dir), patient)


def config_section(cfg: DictConfig, *keys: str) -> dict:
    return {k: OmegaConf.to_container(cfg[k], resolve=True) if isinstance(cfg[k], DictConfig) else cfg[k]
            for k in keys if k in cfg}


def write_sequence_record(paths: PatientPaths, sequence: str, stage: str, files: dict[str, Path]) -> None:
    """``sequence_index/<sequence>.<stage>.json`` = {name: sha256 of the file or folder (:func:`~room_pipeline.io.hashing.sha256_file`), or
    null when the stage did not write it}: what train_depth's DVC dep sees of this sequence."""
    write_json(paths.sequence_record(sequence, stage),
               {k: sha256_file(f) if Path(f).exists() else None for k, f in files.items()})


def metadata(stage: str, patient: str, cfg: DictConfig, keys: tuple[str, ...], **extra: Any) -> dict:
    """Common metadata block of every output: what made it, with which config, in which conventions."""
    return {"stage": stage, "patient": patient, "room_pipeline_version": __version__,
            "config": config_section(cfg, *keys), "conventions": metadata_block(), **extra}


def _cpu_s() -> float:
    """User + system CPU seconds of this process and of its reaped children (worker processes), so far."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                 resource.getrusage(resource.RUSAGE_CHILDREN)))


class StageTimer:
    """Wall time, CPU time and peak resident memory of the stage process.

    ``cpu_s``: user + system CPU of the stage process and of the worker processes it started and reaped inside
    the block (an executor's pool is shut down, so reaped, when its ``with`` block ends)."""

    def __enter__(self) -> "StageTimer":
        self.t0 = time.perf_counter()
        self.c0 = _cpu_s()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.wall_s = time.perf_counter() - self.t0
        self.cpu_s = _cpu_s() - self.c0

    @staticmethod
    def peak_rss_mb() -> float:
        """The largest resident set of one process, the stage's or one of its reaped workers', MiB (workers running
        side by side may together hold more: the render stage reports its own sum, render/sequence.peak_rss_mb)."""
        return max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF,
                                                                 resource.RUSAGE_CHILDREN)) / 1024.0


def write_metrics(paths: PatientPaths, stage: str, metrics: dict, timings: dict | None = None,
                  sequence: str = "") -> None:
    """DVC metrics file of pipeline stage ``stage`` (a name of :data:`room_pipeline.stages.STAGES`) for
    ``sequence`` (empty when the stage does not fan out over sequences) and its timing file; the catalogue
    (:meth:`PatientPaths.stage_metrics`) names both, e.g. ``metrics/render_sequence_000.json``.

    The keys of :data:`room_pipeline.io.metrics.TIMING_KEYS` (wall/CPU times, throughput, peak memory; at any
    dict depth) go to the timing file, so a DVC experiment compares accuracy only; ``timings`` (those taken out
    of the stage's evaluation file by :func:`without_timings`) are merged into it; JSON numbers only
    (NaN -> null), each file written atomically (timings first: the metrics file marks a finished stage).
    """
    write_metrics_file(paths.stage_metrics(stage, sequence), _finite(metrics), _finite(timings or {}))


def without_timings(doc: dict) -> tuple[dict, dict]:
    """``(doc without its timing keys, those timings)`` of an evaluation file (NaN -> null): the file is written
    without them (same inputs -> same bytes) and the timings go to the stage's timing file (:func:`write_metrics`)."""
    return split_timings(_finite(doc))
