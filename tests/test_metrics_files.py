"""Per-stage metrics: accuracy in ``metrics/<stage>.json`` (DVC metric), timings in ``<stage>.timing.json``."""
from __future__ import annotations

import json
import math

from room_pipeline.io.metrics import (TIMING_KEYS, UNITS, is_timing_file, merge_timings, read_metrics,
                                      read_metrics_file, split_timings, timing_path)
from room_pipeline.paths import PatientPaths
from room_pipeline.stages.common import write_metrics

# shaped like the real stages' metrics: flat (mesh), per-method (evaluate_depth), nested dict of times (train_depth)
DOC = {"frames": 448, "AbsRel": 0.08, "wall_time_s": 73.4, "peak_rss_mb": 408.4,
       "time_step_s": 0.01, "duration_s": 44.7,                 # a simulator setting and the route length: kept
       "methods": {"cnn": {"AbsRel": 0.08, "seconds_per_frame": 0.0067, "cpu_seconds_per_frame": 0.0066},
                   "off": {"available": False, "reason": None}},
       "training": {"times_s": {"total": 45.3, "pretrain": 12.9}, "host": {"cpu_count": 2}, "seed": 0,
                    "sequences": [{"frames": 448}]},
       "time_total_s": 4.6, "frames_per_s": 5.3, "realtime_factor": 25.1}


def test_split_moves_every_timing_at_any_depth_and_merge_restores():
    acc, tim = split_timings(DOC)
    assert acc == {"frames": 448, "AbsRel": 0.08, "time_step_s": 0.01, "duration_s": 44.7,
                   "methods": {"cnn": {"AbsRel": 0.08}, "off": {"available": False, "reason": None}},
                   "training": {"seed": 0, "sequences": [{"frames": 448}]}}
    assert tim == {"wall_time_s": 73.4, "peak_rss_mb": 408.4, "time_total_s": 4.6, "frames_per_s": 5.3,
                   "realtime_factor": 25.1,
                   "methods": {"cnn": {"seconds_per_frame": 0.0067, "cpu_seconds_per_frame": 0.0066}},
                   "training": {"times_s": {"total": 45.3, "pretrain": 12.9}, "host": {"cpu_count": 2}}}
    assert merge_timings(acc, tim) == DOC
    assert not TIMING_KEYS & {"time_step_s", "duration_s", "frames"}


def test_empty_and_timing_free_metrics():
    assert split_timings({}) == ({}, {})
    assert split_timings({"a": {}, "b": 1}) == ({"a": {}, "b": 1}, {})
    assert split_timings({"wall_time_s": 1.0}) == ({}, {"wall_time_s": 1.0})


def test_write_metrics_writes_both_files_deterministically(tmp_path):
    paths = PatientPaths(tmp_path, "p")
    write_metrics(paths, "evaluate_depth", {**DOC, "nan_metric": math.nan}, sequence="sequence_000")
    m, t = paths.stage_metrics("evaluate_depth", "sequence_000"), paths.stage_timings("evaluate_depth", "sequence_000")
    assert t == timing_path(m) and t.name == "evaluate_depth_sequence_000.timing.json" and is_timing_file(t)
    assert not is_timing_file(m)
    acc, tim = json.loads(m.read_text()), json.loads(t.read_text())
    assert "wall_time_s" not in m.read_text() and "seconds_per_frame" not in m.read_text()
    assert acc["nan_metric"] is None and tim["units"] == UNITS and tim["wall_time_s"] == 73.4
    assert read_metrics(paths, "evaluate_depth", sequence="sequence_000") == {**DOC, "nan_metric": None}
    assert read_metrics_file(m, timings=False) == acc
    first = (m.read_bytes(), t.read_bytes())
    write_metrics(paths, "evaluate_depth", {**DOC, "nan_metric": math.nan}, sequence="sequence_000")
    assert (m.read_bytes(), t.read_bytes()) == first
    # nothing half-written is left beside them
    assert sorted(f.name for f in paths.metrics_dir.iterdir()) == [m.name, t.name]


def test_read_without_timing_file(tmp_path):
    """Outputs of an older run (timings inside the metrics file, no sibling) still read."""
    f = tmp_path / "mesh.json"
    f.write_text(json.dumps({"n_faces": 3, "wall_time_s": 1.0}))
    assert read_metrics_file(f) == {"n_faces": 3, "wall_time_s": 1.0}
