"""The ``metrics`` section: every stage's metrics merged with its timings, per patient."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..io.metrics import is_timing_file, merge_timings, timing_path
from .common import esc, fmt, na, read_json, html_table
from .options import ReportOptions


def flatten(d: Mapping, prefix: str = "") -> list[tuple[str, Any]]:
    """Leaves of a nested dict as (dotted key, value), keys sorted."""
    out: list[tuple[str, Any]] = []
    for k in sorted(d, key=str):
        v = d[k]
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out += flatten(v, key + ".")
        else:
            out.append((key, v))
    return out


def _headline(doc: Mapping, n: int = 6) -> str:
    skip = {"wall_time_s", "peak_rss_mb"}
    items = [(k, v) for k, v in sorted(doc.items()) if k not in skip and not isinstance(v, (Mapping, list))]
    parts = [f"{k} = {fmt(v)}" for k, v in items[:n]]
    checks = doc.get("checks")
    if isinstance(checks, Mapping) and checks:
        ok = sum(1 for v in checks.values() if v is True)
        parts.insert(0, f"checks passed {ok}/{len(checks)}")
    more = len(items) - n
    return "; ".join(parts) + (f"; ... (+{more} more)" if more > 0 else "")


def section_metrics(opts: ReportOptions, patients: list[Path]) -> str:
    out = []
    for p in patients:
        mdir = p / "metrics"
        out.append(f"<h3>{esc(p.name)}</h3>")
        files = sorted(f for f in mdir.glob("*.json") if not is_timing_file(f)) if mdir.is_dir() else []
        if not files:
            out.append(na(f"no {p.name}/metrics/*.json"))
            continue
        rows, total = [], 0.0
        for f in files:
            doc, why = read_json(f)
            if not isinstance(doc, Mapping):
                rows.append([esc(f.stem), "-", "-", esc(f"not available: {why or 'not a JSON object'}"), ""])
                continue
            tim, _ = read_json(timing_path(f))        # the stage's timings (absent in older outputs)
            if isinstance(tim, Mapping):
                doc = merge_timings(doc, {k: v for k, v in tim.items() if k != "units"})
            wt, rss = doc.get("wall_time_s"), doc.get("peak_rss_mb")
            if isinstance(wt, (int, float)) and not isinstance(wt, bool):
                total += float(wt)
            leaves = flatten(doc)
            details = ("<details><summary>all %d values</summary>" % len(leaves)
                       + html_table(["key", "value"], [(k, fmt(v)) for k, v in leaves], cls="kv") + "</details>")
            rows.append([esc(f.stem), esc(fmt(wt)), esc(fmt(rss)), esc(_headline(doc)), details])
        rows.append(["<b>total</b>", f"<b>{total:.1f}</b>", "", "sum of the stages' wall times", ""])
        out.append(html_table(["stage", "wall time (s)", "peak RSS (MB)", "headline numbers", "details"], rows,
                          raw=True))
    out.append('<p class="note">Wall times and memory depend on the machine and its load when the stage ran.</p>')
    return "\n".join(out) if patients else na("no patients")
