"""The ``benchmarks`` section: speed-vs-error plots, one per benchmark result file that has a plot, each declared
by a :class:`PlotSpec` (which JSON columns make which chart) and drawn by :func:`build_plot` + :func:`plot_png`."""
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


@dataclasses.dataclass(frozen=True)
class Line:
    """One line per group of a :class:`PlotSpec`: its y column, label (``str.format`` over the group's columns,
    with :attr:`PlotSpec.names` applied) and matplotlib style; ``style_by``: style key -> (column, {value: style})."""

    y: str
    label: str
    style: Mapping = dataclasses.field(default_factory=dict)
    style_by: Mapping = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class PlotSpec:
    """Which columns of a benchmark result file make its chart, read by :func:`build_plot`.

    ``rows``: the key of the row list (or, for ``kind="bar"``, of a {name: row} mapping, bars sorted by name);
    ``group``: columns whose distinct values (sorted; in order of ``group_order`` where given) make one group;
    rows of a group sorted by ``sort``, ``x`` against each :class:`Line`'s y.  ``points``: every row its own
    point series (the group's label on its first only) with the marker of ``marker_by``'s value (sorted values
    cycling through :data:`MARKERS`; the caption lists them).  ``flag``: (column, value, style) -- the group's
    rows with that value drawn again in that style, unlabelled, captioned ``flag_note``.  ``note``: caption
    (``str.format``; ``{values}``: the distinct values of column ``note_values`` (times ``note_scale``), ``%g``
    joined by ", ").  ``colour_by_group``: a group's lines share a colour."""

    stem: str
    title: str
    xlabel: str
    ylabel: str
    rows: str
    x: str = ""
    group: tuple[str, ...] = ()
    sort: str = ""
    lines: tuple[Line, ...] = ()
    group_order: Mapping = dataclasses.field(default_factory=dict)
    names: Mapping = dataclasses.field(default_factory=dict)
    points: bool = False
    marker_by: str = ""
    flag: tuple = ()
    flag_note: str = ""
    note: str = ""
    note_values: str = ""
    note_scale: float = 1.0
    colour_by_group: bool = False
    logx: bool = False
    logy: bool = False
    kind: str = "line"


MARKERS = "os^Dv<>p"

#: benchmark result file stem -> chart (in page order)
BENCHMARK_PLOTS: tuple[PlotSpec, ...] = (
    PlotSpec("mesh_decimation", "Mesh decimation: faces vs surface error", "faces (fewer = faster downstream)",
             "distance to the exact surface (voxels)", rows="rows", x="n_faces", group=("case",), sort="n_faces",
             lines=(Line("mean_vox", "{case}: mean", {"marker": "o"}),
                    Line("p95_vox", "{case}: p95", {"marker": "s", "ls": "--"})), colour_by_group=True, logx=True),
    PlotSpec("sdf_methods", "SDF from a mask: time vs error", "wall time (s)", "MAE (voxels)", rows="rows",
             x="wall_s", group=("method",), lines=(Line("mae_vox", "{method}", {"ls": "none"}),), points=True,
             marker_by="case", colour_by_group=True, logx=True),
    PlotSpec("simulation", "Scope simulation: cost vs tip error", "wall s per simulated s (free space)",
             "max tip error (mm)", rows="speed_vs_error", x="wall_s_per_sim_s_free", group=("n_links",),
             sort="time_step_s", lines=(Line("tip_error_mm_max", "{n_links} links", {"marker": "o"}),),
             flag=("stable", False, {"marker": "x", "ls": "none", "color": "k", "ms": 9}), flag_note="; x = unstable",
             note="points along a line: time steps {values} ms", note_values="time_step_s", note_scale=1e3,
             logy=True),
    PlotSpec("raycast_renderer", "Fast renderer: time per frame (speed only, no error axis)", "ms per frame", "",
             rows="runs", lines=(Line("ms_per_frame", "{name}"),), kind="bar"),
    PlotSpec("cycles_quality", "Cycles: time per frame vs PSNR", "time per frame (s)", "PSNR vs reference (dB)",
             rows="quality", x="time_s", group=("view", "denoise"), sort="spp", group_order={"denoise": (False, True)},
             names={"denoise": {False: "no denoiser", True: "OIDN"}},
             lines=(Line("psnr_db", "view {view}, {denoise}", {"marker": "o"}, {"ls": ("denoise", {True: "-", False: "--"})}),),
             note="points along a line: {values} spp", note_values="spp", logx=True),
)


def _groups(spec: PlotSpec, rows: list) -> list[tuple]:
    """The distinct values of the group columns, sorted column by column (``group_order`` first)."""
    keys = {tuple(bool(r[c]) if c in spec.group_order else r[c] for c in spec.group) for r in rows}
    order = [(lambda v, c=c: spec.group_order[c].index(v)) if c in spec.group_order else (lambda v: v)
             for c in spec.group]
    return sorted(keys, key=lambda k: tuple(f(v) for f, v in zip(order, k)))


def build_plot(spec: PlotSpec, doc: Mapping) -> Plot:
    """The :class:`Plot` of benchmark result ``doc`` as ``spec`` says (KeyError etc. on another structure)."""
    if spec.kind == "bar":
        runs = doc[spec.rows]
        line = spec.lines[0]
        return Plot(spec.title, spec.xlabel, spec.ylabel,
                    [(line.label.format(name=n), [runs[n][line.y]], [0], {}) for n in sorted(runs)], kind="bar")
    rows = doc[spec.rows]
    marks = sorted({r[spec.marker_by] for r in rows}) if spec.points else []
    series = []
    for key in _groups(spec, rows):
        g = [r for r in rows if tuple(bool(r[c]) if c in spec.group_order else r[c] for c in spec.group) == key]
        if spec.sort:
            g = sorted(g, key=lambda r: r[spec.sort])
        if not g:
            continue
        fields = {c: spec.names.get(c, {}).get(v, v) for c, v in zip(spec.group, key)}
        group = {"group": "/".join(str(v) for v in key)} if spec.colour_by_group else {}
        for line in spec.lines:
            style = {**line.style, **{k: m[dict(zip(spec.group, key))[c]] for k, (c, m) in line.style_by.items()},
                     **group}
            label = line.label.format(**fields)
            if spec.points:
                series += [(label if r is g[0] else None, [r[spec.x]], [r[line.y]],
                            {"marker": MARKERS[marks.index(r[spec.marker_by]) % len(MARKERS)], **style}) for r in g]
            else:
                series.append((label, [r[spec.x] for r in g], [r[line.y] for r in g], style))
            if spec.flag:
                bad = [r for r in g if r.get(spec.flag[0]) is spec.flag[1]]
                if bad:
                    series.append((None, [r[spec.x] for r in bad], [r[line.y] for r in bad], dict(spec.flag[2])))
    note = spec.note and spec.note.format(values=", ".join(f"{spec.note_scale * v:g}"
                                                            for v in sorted({r[spec.note_values] for r in rows})))
    if spec.flag and any(r.get(spec.flag[0]) is spec.flag[1] for r in rows):
        note += spec.flag_note
    if spec.points:
        note = "marker = " + spec.marker_by + ": " + ", ".join(f"{MARKERS[i % len(MARKERS)]} {c}"
                                                             for i, c in enumerate(marks))
    return Plot(spec.title, spec.xlabel, spec.ylabel, series, logx=spec.logx, logy=spec.logy, note=note)


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
    for spec in BENCHMARK_PLOTS:
        stem = spec.stem
        f = d / f"{stem}.json"
        doc, why = read_json(f)
        if doc is None:
            figs.append(f'<figure class="plot">{na(f"{stem}: {why}")}</figure>')
            continue
        try:
            plot = build_plot(spec, doc)
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
