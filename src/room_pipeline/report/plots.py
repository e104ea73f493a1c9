"""The ``benchmarks`` section: speed-vs-error plots, one per benchmark result file that has a plot."""
from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path
from typing import Callable, Mapping

from .common import esc, img_tag, na, read_json, show_path, html_table, data_uri
from .options import ReportOptions


@dataclasses.dataclass
class Plot:
    """One speed-vs-error chart: series of (label, x, y, style dict)."""

    title: str
    xlabel: str
    ylabel: str
    series: list
    logx: bool = False
    logy: bool = False
    note: str = ""
    kind: str = "line"        # "line" or "bar"


def _plot_mesh_decimation(d: Mapping) -> Plot:
    series = []
    for case in sorted({r["case"] for r in d["rows"]}):
        rows = sorted((r for r in d["rows"] if r["case"] == case), key=lambda r: r["n_faces"])
        series.append((f"{case}: mean", [r["n_faces"] for r in rows], [r["mean_vox"] for r in rows],
                       {"marker": "o", "group": case}))
        series.append((f"{case}: p95", [r["n_faces"] for r in rows], [r["p95_vox"] for r in rows],
                       {"marker": "s", "ls": "--", "group": case}))
    return Plot("Mesh decimation: faces vs surface error", "faces (fewer = faster downstream)",
                "distance to the exact surface (voxels)", series, logx=True)


def _plot_sdf_methods(d: Mapping) -> Plot:
    markers = "os^Dv<>p"
    cases = sorted({r["case"] for r in d["rows"]})
    series = []
    for m in sorted({r["method"] for r in d["rows"]}):
        rows = [r for r in d["rows"] if r["method"] == m]
        for r in rows:
            series.append((m if r is rows[0] else None, [r["wall_s"]], [r["mae_vox"]],
                           {"marker": markers[cases.index(r["case"]) % len(markers)], "ls": "none", "group": m}))
    return Plot("SDF from a mask: time vs error", "wall time (s)", "MAE (voxels)", series, logx=True,
                note="marker = case: " + ", ".join(f"{markers[i % len(markers)]} {c}" for i, c in enumerate(cases)))


def _plot_simulation(d: Mapping) -> Plot:
    rows = d["speed_vs_error"]
    series = []
    for n in sorted({r["n_links"] for r in rows}):
        rs = sorted((r for r in rows if r["n_links"] == n), key=lambda r: r["time_step_s"])
        series.append((f"{n} links", [r["wall_s_per_sim_s_free"] for r in rs], [r["tip_error_mm_max"] for r in rs],
                       {"marker": "o"}))
        bad = [r for r in rs if r.get("stable") is False]
        if bad:
            series.append((None, [r["wall_s_per_sim_s_free"] for r in bad], [r["tip_error_mm_max"] for r in bad],
                           {"marker": "x", "ls": "none", "color": "k", "ms": 9}))
    return Plot("Scope simulation: cost vs tip error", "wall s per simulated s (free space)", "max tip error (mm)",
                series, logy=True, note="points along a line: time steps " + ", ".join(
                    f"{1e3 * t:g}" for t in sorted({r['time_step_s'] for r in rows})) + " ms"
                + ("; x = unstable" if any(r.get("stable") is False for r in rows) else ""))


def _plot_cycles(d: Mapping) -> Plot:
    rows = d["quality"]
    series = []
    for view in sorted({r["view"] for r in rows}):
        for dn in (False, True):
            rs = sorted((r for r in rows if r["view"] == view and bool(r["denoise"]) == dn), key=lambda r: r["spp"])
            if rs:
                series.append((f"view {view}, {'OIDN' if dn else 'no denoiser'}", [r["time_s"] for r in rs],
                               [r["psnr_db"] for r in rs], {"marker": "o", "ls": "-" if dn else "--"}))
    return Plot("Cycles: time per frame vs PSNR", "time per frame (s)", "PSNR vs reference (dB)", series, logx=True,
                note="points along a line: " + ", ".join(str(s) for s in sorted({r["spp"] for r in rows})) + " spp")


def _plot_raycast(d: Mapping) -> Plot:
    runs = d["runs"]
    names = sorted(runs)
    return Plot("Fast renderer: time per frame (speed only, no error axis)", "ms per frame", "",
                [(n, [runs[n]["ms_per_frame"]], [0], {}) for n in names], kind="bar")


#: benchmark result file stem -> chart builder (in page order)
BENCHMARK_PLOTS: tuple[tuple[str, Callable[[Mapping], Plot]], ...] = (
    ("mesh_decimation", _plot_mesh_decimation),
    ("sdf_methods", _plot_sdf_methods),
    ("simulation", _plot_simulation),
    ("raycast_renderer", _plot_raycast),
    ("cycles_quality", _plot_cycles),
)


def plot_png(plot: Plot, size_in: tuple[float, float] = (5.6, 3.6), dpi: int = 100) -> bytes:
    """Draw a :class:`Plot` with matplotlib (Agg, no global state) into PNG bytes (no time stamp)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, NullFormatter

    fig = Figure(figsize=size_in, dpi=dpi)
    ax = fig.add_subplot()
    if plot.kind == "bar":
        labels = [s[0] for s in plot.series]
        vals = [s[1][0] for s in plot.series]
        ax.barh(range(len(vals)), vals, color="#4a78c2")
        ax.set_yticks(range(len(vals)), labels, fontsize=8)
        ax.invert_yaxis()
    else:
        colours = {}
        for label, xs, ys, style in plot.series:
            st = dict(style)
            group = st.pop("group", label)
            if "color" not in st and group is not None:
                st["color"] = colours.setdefault(group, f"C{len(colours) % 10}")
            ax.plot(xs, ys, label=label, ms=st.pop("ms", 5), **st)
        if any(s[0] for s in plot.series):
            ax.legend(fontsize=7, loc="best")
        plain = FuncFormatter(lambda v, _: f"{v:g}")
        # minor ticks labelled at 2 and 5 times a power of ten (plain numbers, not 2x10^-1)
        two_five = FuncFormatter(lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v)))
                                 in (2, 5) else "")
        for on, axis, scale in ((plot.logx, ax.xaxis, ax.set_xscale), (plot.logy, ax.yaxis, ax.set_yscale)):
            if on:
                scale("log")
                lo, hi = axis.get_view_interval()
                axis.set_major_formatter(plain)
                axis.set_minor_formatter(two_five if hi < 1000 * lo else NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
    ax.set_xlabel(plot.xlabel)
    if plot.ylabel:
        ax.set_ylabel(plot.ylabel)
    ax.set_title(plot.title, fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _md_title(path: Path) -> str:
    try:
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.startswith("#"):
                return line.lstrip("#").strip()
    except (OSError, UnicodeDecodeError):
        return "(unreadable)"
    return "(no title)"


def section_benchmarks(opts: ReportOptions) -> str:
    d = opts.benchmarks_dir
    if d is None or not Path(d).is_dir():
        return na(f"no benchmark results folder ({show_path(d, opts.base) if d else 'none given'})")
    d = Path(d)
    out, figs = [], []
    for stem, builder in BENCHMARK_PLOTS:
        f = d / f"{stem}.json"
        doc, why = read_json(f)
        if doc is None:
            figs.append(f'<figure class="plot">{na(f"{stem}: {why}")}</figure>')
            continue
        try:
            plot = builder(doc)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            figs.append(f'<figure class="plot">{na(f"{stem}.json has an unexpected structure ({exc!r})")}</figure>')
            continue
        uri = data_uri(plot_png(plot), "image/png")
        cap = f"{stem}.json" + (f"; {plot.note}" if plot.note else "")
        figs.append(f'<figure class="plot">{img_tag(uri, plot.title, 560, 360)}'
                    f"<figcaption>{esc(cap)}</figcaption></figure>")
    out.append(f'<div class="plots">{"".join(figs)}</div>')
    mds = sorted(d.glob("*.md"))
    if mds:
        out.append("<h3>All benchmark results</h3>")
        out.append(html_table(["file", "title"], [(m.name, _md_title(m)) for m in mds]))
    out.append('<p class="note">Timings were measured on shared machines; each result file states its command '
               "and the machine load.</p>")
    return "\n".join(out)
