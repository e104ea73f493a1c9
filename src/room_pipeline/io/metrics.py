"""Per-stage metrics files: accuracy in the DVC metrics file, timings beside it.

Every stage writes ``metrics/<stage>.json`` (a DVC *metric*: what a config change is compared on, e.g.
``dvc exp show --only-changed`` after ``dvc exp run -S noise.beta=0.5``) and ``metrics/<stage>.timing.json``
(a plain uncached DVC *out*: wall/CPU times, throughput, peak memory, the host they were measured on; these
change from run to run and machine to machine, so they are kept out of the comparison).

:func:`split_timings` decides which keys are timings: a key is a timing when its name is in
:data:`TIMING_KEYS` (the one list; a whole sub-dict moves when its key is listed, e.g. ``times_s``), at any
depth of nested dicts (lists are kept as they are).  The timing file mirrors the metrics file's nesting, plus
a ``units`` block; :func:`read_metrics` merges both back for readers that want the timings (the HTML report,
benchmarks).

The evaluation stages' data files (``evaluation/<patient>/<sequence>/pose.json``, ``depth.json``,
``depth_errors.csv``, ``evaluation/<patient>/depth_finetune.json``) hold no timing either: the stage writes the
file's timing keys into its own ``metrics/<stage>.timing.json`` under the file's own top-level key
(``methods`` / ``datasets``), so the same inputs give the same bytes; :func:`read_with_timings` merges them
back (the tables, benchmarks).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .atomic import write_json

#: key names that are timings or resource use, not accuracy (moved to ``<stage>.timing.json``):
#: ``wall_time_s`` stage wall time; ``peak_rss_mb`` peak resident memory of the stage process (MiB);
#: ``frames_per_s`` / ``seconds_per_frame`` / ``cpu_seconds_per_frame`` / ``seconds_per_frame_all_methods``
#: throughput; ``realtime_factor`` simulated seconds per wall second; ``filter_table_s``,
#: ``synthesis_ms_per_frame`` (noise), ``time_{prepare,surface,trace,graph,total}_s`` (medial axis) step
#: times; ``times_s`` (train_depth: a dict of step times) and ``host`` (the CPU they were measured on).
#: ``cpu_time_s`` stage CPU time; ``seconds`` / ``cpu_seconds`` (a pose method's wall / CPU time) and
#: ``frame_seconds`` (a depth method's wall time per frame, a list) from the evaluation files.
#: Not ``time_step_s`` (the simulator's fixed physics step, a setting) nor ``duration_s`` (route duration).
TIMING_KEYS = frozenset({
    "wall_time_s", "peak_rss_mb", "frames_per_s", "seconds_per_frame", "cpu_seconds_per_frame",
    "seconds_per_frame_all_methods", "realtime_factor", "filter_table_s", "synthesis_ms_per_frame",
    "time_prepare_s", "time_surface_s", "time_trace_s", "time_graph_s", "time_total_s", "times_s", "host",
    "cpu_time_s", "seconds", "cpu_seconds", "frame_seconds",
})

#: written in every timing file (and dropped again by :func:`read_metrics`)
UNITS = {"*_s, *_per_frame, times_s, seconds, frame_seconds": "seconds (wall clock unless named cpu_*)", "*_ms_per_frame": "milliseconds",
         "peak_rss_mb": "MiB (ru_maxrss / 1024)", "frames_per_s": "frames per wall-clock second",
         "realtime_factor": "simulated seconds per wall-clock second"}

TIMING_SUFFIX = ".timing.json"


def timing_path(metrics_path: str | Path) -> Path:
    """``metrics/<stage>.json`` -> ``metrics/<stage>.timing.json``."""
    p = Path(metrics_path)
    return p.with_name(p.name[:-len(".json")] + TIMING_SUFFIX if p.name.endswith(".json") else p.name + TIMING_SUFFIX)


def is_timing_file(path: str | Path) -> bool:
    return Path(path).name.endswith(TIMING_SUFFIX)


def split_timings(metrics: dict) -> tuple[dict, dict]:
    """``(accuracy, timings)``: the keys of :data:`TIMING_KEYS` (at any dict depth) go to ``timings``."""
    acc: dict = {}
    tim: dict = {}
    for k, v in metrics.items():
        if k in TIMING_KEYS:
            tim[k] = v
        elif isinstance(v, dict):
            a, t = split_timings(v)
            acc[k] = a
            if t:
                tim[k] = t
        else:
            acc[k] = v
    return acc, tim


def merge_timings(metrics: dict, timings: dict) -> dict:
    """Inverse of :func:`split_timings`: ``timings`` deep-merged into a copy of ``metrics``."""
    out = dict(metrics)
    for k, v in timings.items():
        out[k] = merge_timings(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def write_metrics_file(path: str | Path, metrics: dict, timings: dict | None = None) -> None:
    """``path`` (a DVC metrics file) and its ``.timing.json`` sibling, from one dict split by
    :func:`split_timings`: the metric gets the accuracy keys only, so the same config gives the same bytes.
    ``timings`` (e.g. an evaluation file's, see :func:`read_with_timings`) are deep-merged into the timing file.
    Each file is written atomically, timings first (the metrics file marks a finished stage).  A ``units``
    entry that names a timing key moves with it; the timing file's ``units`` also carries :data:`UNITS`."""
    accuracy, tim = split_timings(metrics)
    tim = merge_timings(tim, timings or {})
    write_json(timing_path(path), {**tim, "units": {**(tim.get("units") or {}), **UNITS}})
    write_json(path, accuracy)


def read_with_timings(path: str | Path, timing_file: str | Path) -> dict:
    """An evaluation file (``pose.json``, ``depth.json``, ``depth_finetune.json``) with the timings its stage
    moved to ``timing_file`` (``metrics/<stage>.timing.json``: the entries under the file's own top-level keys,
    e.g. ``methods.<name>.seconds_per_frame``) merged back; the file alone when there is no timing file."""
    with open(path, encoding="utf-8") as fh:
        doc = json.load(fh)
    t = Path(timing_file)
    if not t.is_file():
        return doc
    with open(t, encoding="utf-8") as fh:
        tim = json.load(fh)
    return merge_timings(doc, {k: v for k, v in tim.items() if k in doc and isinstance(v, dict)})


def read_metrics_file(path: str | Path, timings: bool = True) -> dict:
    """A stage's metrics file, merged with its ``.timing.json`` sibling when ``timings`` (and it exists)."""
    with open(path, encoding="utf-8") as fh:
        doc = json.load(fh)
    t = timing_path(path)
    if timings and t.is_file():
        with open(t, encoding="utf-8") as fh:
            tim = json.load(fh)
        tim.pop("units", None)
        doc = merge_timings(doc, tim)
    return doc


def read_metrics(paths: Any, stage: str, timings: bool = True, sequence: str = "") -> dict:
    """``paths.stage_metrics(stage, sequence)`` (a :class:`~room_pipeline.paths.PatientPaths`) read by
    :func:`read_metrics_file`."""
    return read_metrics_file(paths.stage_metrics(stage, sequence), timings=timings)
