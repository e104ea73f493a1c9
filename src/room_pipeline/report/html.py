"""``room report``: a self-contained HTML report of a generated dataset (one file, no network).

Sections (``<section id=...>``, in this order, see :data:`SECTIONS`)
    ``summary``     patients, sequences, planned / simulated / rendered frame counts, camera, and the
                    conventions (units, frames) of :mod:`room_pipeline.conventions`.
    ``thumbnails``  a few evenly spaced frames per rendered sequence, one column per modality:
                    RGB as is; depth (viridis, range in mm stated, with a colour bar); relative
                    inverse depth (magma, 0..1); normals ((n + 1) / 2 of the camera-frame x, y, z as
                    R, G, B); optical flow (hue = direction, saturation = magnitude up to a stated
                    maximum, with a colour wheel); segmentation (one colour per branch label).
                    Pixels without a surface hit (or without valid flow) are black.
    ``view3d``      per sequence, the airway mesh (semi-transparent), the planned trajectory, the
                    simulated tip path, the rendered cameras and the scope at a few frames, drawn
                    off-screen by pyvista (VTK; Mesa EGL/OSMesa when there is no display), or by
                    matplotlib 3-D when pyvista cannot render (the caption says which).  The scope
                    is a tube of the recorded outer diameter along the backbone reconstructed from
                    the simulated joints (``q_act``): the shaft on the planned route up to the
                    insertion ``q3`` (the simulator's ``kinematic`` insertion model), then the
                    constant-curvature bending segment; the caption gives, per drawn frame, the
                    distance between that model tip and the simulated tip pose.
    ``metrics``     per patient, every ``metrics/*.json`` merged with its ``*.timing.json``: wall time,
                    peak RSS, the headline numbers and (collapsed) every recorded value.
    ``benchmarks``  speed-vs-error plots (matplotlib, Agg) from ``benchmarks/results/*.json`` and
                    the list of result files with their titles.
    ``tables``      the paper tables ``table_*.md`` (else ``table_*.csv``) of the `tables` stage.

Anything absent is one line ``not available: <why>``; nothing is invented.  Images are
``data:`` URIs (PNG; JPEG for the 3-D views); the page carries a Content-Security-Policy that
forbids any other source, and a small inline script that, after ``window.onload``, writes
``data-images-loaded="<loaded>/<total>"`` on ``<body>`` (what the browser test reads).
Deterministic: same inputs -> same bytes (sorted iteration, no time stamps, paths shown relative
to the project folder; the 3-D images depend on the OpenGL implementation).
"""
from __future__ import annotations

import argparse
import base64
import dataclasses
import functools
import html
import io
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from ..catalog import (METADATA, RENDER_JSON, RGB_NOISY, RGB_SOURCES, SIMULATION_JSON, TRAJECTORY_JSON,
                       SequencePaths)
from ..errors import ConfigError, InputError, RoomError
from ..io.metrics import is_timing_file, merge_timings, timing_path
from ..io.records import POSE_KEY, pose_track_from_doc

#: (section id, heading), in page order
SECTIONS: tuple[tuple[str, str], ...] = (
    ("summary", "Dataset summary"),
    ("thumbnails", "Modalities"),
    ("realism", "Real vs synthetic frames"),
    ("view3d", "Trajectory and scope in the airway (3-D)"),
    ("metrics", "Per-stage metrics and timings"),
    ("benchmarks", "Speed vs error (benchmarks)"),
    ("tables", "Paper tables"),
)
#: modalities shown as thumbnails, in column order (those the sequence has)
THUMB_MODALITIES = ("rgb", RGB_NOISY, "depth", "relative_depth", "normals", "flow", "segmentation")
#: colours of the 3-D view (RGB 0..1), also used by the legend
COLOURS = {"airway": (0.86, 0.62, 0.56), "planned": (0.16, 0.35, 0.85), "simulated": (0.95, 0.50, 0.05),
           "rendered": (0.10, 0.65, 0.25), "scope": (0.25, 0.25, 0.28), "tip": (0.85, 0.05, 0.10)}
_MARKERS = ("metrics", "anatomy", "input", "ground_truth")


@dataclasses.dataclass(frozen=True)
class ReportOptions:
    """What goes into the report.

    Attributes:
        output_dir: the dataset root (``<output_dir>/<patient>/...``).
        benchmarks_dir: ``benchmarks/results`` (None: the section says why it is empty).
        tables_dir: where the `tables` stage writes ``table_*.md`` (None: likewise).
        max_frames: thumbnail rows per sequence (evenly spaced frames), >= 1.
        thumb_px: longest side of a thumbnail, pixels.
        view_size: (width, height) of a 3-D view, pixels.
        scope_frames: frames at which the scope is drawn, >= 0.
        base: folder the shown paths are relative to (default: the current folder).
        use_pyvista: False forces the matplotlib 3-D fallback.
        real_dir: real bronchoscopy frames shown beside ours (None: the section says why it is empty).
    """

    output_dir: Path
    benchmarks_dir: Path | None = None
    tables_dir: Path | None = None
    max_frames: int = 4
    thumb_px: int = 160
    view_size: tuple[int, int] = (600, 540)
    scope_frames: int = 3
    base: Path | None = None
    use_pyvista: bool = True
    real_dir: Path | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.max_frames, int) or self.max_frames < 1:
            raise ConfigError(f"report: max_frames must be an integer >= 1, got {self.max_frames!r}")
        if self.thumb_px < 16 or min(self.view_size) < 64 or self.scope_frames < 0:
            raise ConfigError("report: thumb_px >= 16, view_size >= 64 px and scope_frames >= 0 required")


# =========================================================================== small helpers


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _na(why: str) -> str:
    return f'<p class="na">not available: {_esc(why)}</p>'


def _fmt(v: Any) -> str:
    """A value as table text: floats to 4 significant digits, bools yes/no, short lists inline."""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.4g}"
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        items = [_fmt(x) for x in v[:6]]
        return "[" + ", ".join(items) + (", ..." if len(v) > 6 else "") + "]"
    return str(v)


def _show(path: Path, base: Path | None) -> str:
    """``path`` relative to ``base`` when inside it (stable across clones), else as given."""
    p = Path(path)
    try:
        return p.resolve().relative_to((base or Path.cwd()).resolve()).as_posix() or "."
    except ValueError:
        return p.as_posix()


def _read_json(path: Path) -> tuple[Any, str | None]:
    """(document, None), or (None, why) when the file is absent or not JSON."""
    if not path.is_file():
        return None, f"no {path.name}"
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh), None
    except (OSError, ValueError) as exc:
        return None, f"{path.name} is not readable JSON ({exc.__class__.__name__})"


def _uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def png_uri(rgb: np.ndarray) -> str:
    """A (H, W) grey or (H, W, 3) RGB uint8 array as a PNG ``data:`` URI (deterministic bytes)."""
    import cv2

    a = np.ascontiguousarray(rgb)
    if a.ndim == 3:
        a = np.ascontiguousarray(a[..., ::-1])
    ok, buf = cv2.imencode(".png", a, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 PNG
        raise RuntimeError("PNG encoding failed")
    return _uri(buf.tobytes(), "image/png")


def jpeg_uri(rgb: np.ndarray, quality: int = 90) -> str:
    """A (H, W, 3) RGB uint8 array as a JPEG ``data:`` URI."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover
        raise RuntimeError("JPEG encoding failed")
    return _uri(buf.tobytes(), "image/jpeg")


def _img(uri: str, alt: str, width: int, height: int, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img{c} src="{uri}" alt="{_esc(alt)}" width="{width}" height="{height}">'


def _table(header: Sequence[str], rows: Iterable[Sequence[str]], cls: str = "data", raw: bool = False) -> str:
    """An HTML table; cells are escaped unless ``raw``."""
    f = (lambda c: c) if raw else _esc
    out = [f'<table class="{cls}"><thead><tr>' + "".join(f"<th>{f(h)}</th>" for h in header) + "</tr></thead><tbody>"]
    out += ["<tr>" + "".join(f"<td>{f(c)}</td>" for c in row) + "</tr>" for row in rows]
    out.append("</tbody></table>")
    return "".join(out)


# =========================================================================== colour mapping (pure)


@functools.lru_cache(maxsize=None)
def _lut(name: str) -> np.ndarray:
    """The 256-entry uint8 RGB table of a matplotlib colour map (read-only)."""
    import matplotlib

    lut = np.rint(matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def colorize(values: np.ndarray, vmin: float, vmax: float, cmap: str = "viridis",
             valid: np.ndarray | None = None) -> np.ndarray:
    """Scalar image -> (H, W, 3) uint8 through a matplotlib colour map, clipped to [vmin, vmax];
    black where not ``valid``."""
    v = np.asarray(values, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    t = np.clip((np.nan_to_num(v) - vmin) / span, 0.0, 1.0)
    out = _lut(cmap)[np.rint(t * 255).astype(np.int64)]
    if valid is not None:
        out[~np.asarray(valid, bool)] = 0
    return out


def normals_rgb(normals: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Unit normals (camera frame) -> RGB = (n + 1) / 2 of (x, y, z); black where not valid (or n = 0)."""
    n = np.asarray(normals, dtype=np.float64)
    out = np.rint(np.clip((n + 1.0) * 0.5, 0.0, 1.0) * 255).astype(np.uint8)
    ok = np.any(n != 0, axis=-1) if valid is None else np.asarray(valid, bool)
    out[~ok] = 0
    return out


def flow_rgb(flow: np.ndarray, valid: np.ndarray | None, max_px: float) -> np.ndarray:
    """Optical flow (pixels, u along columns, v along rows) -> RGB: hue = direction, saturation =
    magnitude / ``max_px`` (clipped to 1), black where not valid.  Hue 0 (red) = +u (right)."""
    import cv2

    f = np.asarray(flow, dtype=np.float64)
    u, v = f[..., 0], f[..., 1]
    ang = np.mod(np.arctan2(v, u), 2 * np.pi)
    hsv = np.empty(u.shape + (3,), np.uint8)
    hsv[..., 0] = np.rint(ang / (2 * np.pi) * 180).astype(np.int64) % 180
    hsv[..., 1] = np.rint(np.clip(np.hypot(u, v) / max(max_px, 1e-12), 0, 1) * 255).astype(np.uint8)
    hsv[..., 2] = 255
    out = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if valid is not None:
        out[~np.asarray(valid, bool)] = 0
    return out


def labels_rgb(labels: np.ndarray) -> np.ndarray:
    """Integer labels -> RGB, a fixed colour per label (golden-ratio hues), 0 (no hit) black."""
    import matplotlib.colors as mcolors

    lab = np.asarray(labels).astype(np.int64)
    ids, inv = np.unique(lab, return_inverse=True)
    hue = np.mod(ids * 0.6180339887498949, 1.0)
    sat = 0.55 + 0.35 * np.mod(ids * 0.37, 1.0)
    pal = np.rint(mcolors.hsv_to_rgb(np.stack([hue, sat, np.full_like(hue, 0.95)], -1)) * 255).astype(np.uint8)
    pal[ids == 0] = 0
    return pal[inv.reshape(lab.shape)]


def colour_bar(cmap: str, width: int = 160, height: int = 10) -> np.ndarray:
    """A horizontal colour bar (low values on the left)."""
    return colorize(np.tile(np.linspace(0, 1, width), (height, 1)), 0.0, 1.0, cmap)


def flow_wheel(size: int = 48) -> np.ndarray:
    """The flow colour key: a disc whose pixel at (u, v) from the centre has that flow's colour (radius = max)."""
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    f = np.stack([xx - c, yy - c], -1)
    return flow_rgb(f, np.hypot(f[..., 0], f[..., 1]) <= c, c)


def thumbnail(img: np.ndarray, px: int, nearest: bool = False) -> np.ndarray:
    """Downscale so the longer side is ``px`` (area averaging; ``nearest`` for labels); never upscales."""
    import cv2

    h, w = img.shape[:2]
    s = px / max(h, w)
    if s >= 1.0:
        return np.ascontiguousarray(img)
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return cv2.resize(img, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def pick_frames(n: int, k: int) -> list[int]:
    """``k`` evenly spaced positions in 0..n-1 (first and last included), sorted, unique."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(k, n))})


# =========================================================================== dataset discovery


def find_patients(output_dir: Path) -> list[Path]:
    """Patient folders under ``output_dir`` (sorted): those with metrics/, anatomy/, input/,
    ground_truth/ or a sequence folder (a sub-folder holding ``metadata/``)."""
    out = []
    for d in sorted(p for p in Path(output_dir).iterdir() if p.is_dir() and not p.name.startswith(".")):
        if any((d / m).is_dir() for m in _MARKERS) or find_sequence_dirs(d):
            out.append(d)
    return out


def find_sequence_dirs(patient: Path) -> list[Path]:
    """Sequence folders of a patient (sorted): sub-folders holding ``metadata/``."""
    return sorted(p for p in Path(patient).iterdir()
                  if p.is_dir() and not p.name.startswith(".") and (p / METADATA).is_dir())


# =========================================================================== section: summary


def _sequence_row(seq: Path) -> list[str]:
    from ..dataset.reader import SequenceReader, is_sequence

    traj, why_t = _read_json(SequencePaths(seq).trajectory)
    sim, why_s = _read_json(SequencePaths(seq).simulation)
    has = lambda doc: isinstance(doc, dict) and bool(doc.get("frames"))  # noqa: E731
    planned = f"{len(traj['frames'])}" if has(traj) else f"- ({why_t or 'no frames'})"
    if isinstance(traj, dict) and isinstance(traj.get("summary"), dict) and "length_m" in traj["summary"]:
        planned += f", {1e3 * float(traj['summary']['length_m']):.1f} mm"
    tgt = traj.get("target") if isinstance(traj, dict) else None
    if isinstance(tgt, dict) and "stop_distance" in tgt:  # how far from the target the scope stopped, and why
        planned += f"; stopped {1e3 * float(tgt['stop_distance']):.1f} mm from the target ({tgt.get('stop_reason', '?')})"
    simulated = f"{len(sim['frames'])}" if has(sim) else f"- ({why_s or 'no frames'})"
    if is_sequence(seq):
        try:
            r = SequenceReader(seq)
        except InputError as exc:
            return [seq.parent.name, seq.name, planned, simulated, f"- ({exc})", "-", "-", "-"]
        i = r.intrinsics
        fov = math.degrees(2 * math.atan(i["width"] / (2 * i["fx"])))
        backend = (r.render_meta.get("renderer") or {}).get("backend", "?")
        poses = r.render_meta.get("poses", "?")
        rendered = f"{len(r)} ({backend}, {poses} poses)"
        span = float(r.timestamps[-1] - r.timestamps[0]) if len(r) > 1 else 0.0
        return [seq.parent.name, seq.name, planned, simulated, rendered,
                f"{i['width']}x{i['height']}, fx {i['fx']:.1f} px, fov_x {fov:.1f} deg",
                ", ".join(r.modalities), f"{span:.2f}"]
    return [seq.parent.name, seq.name, planned, simulated, "- (not rendered: no metadata/render.json)", "-", "-", "-"]


def section_summary(opts: ReportOptions, patients: list[Path]) -> str:
    from ..conventions import metadata_block

    if not patients:
        return _na(f"no patient folders in {_show(opts.output_dir, opts.base)}")
    from ..dataset.reader import is_sequence

    rows, counts, n_rendered = [], [], 0
    for p in patients:
        seqs = find_sequence_dirs(p)
        counts.append(len(seqs))
        n_rendered += sum(1 for s in seqs if is_sequence(s))
        rows += [_sequence_row(s) for s in seqs]
    out = [f"<p>{len(patients)} patient(s), {sum(counts)} sequence(s) with metadata, {n_rendered} rendered, "
           f"in <code>{_esc(_show(opts.output_dir, opts.base))}</code>.</p>"]
    for p, n in zip(patients, counts):
        if n == 0:
            out.append(f"<p>{_esc(p.name)}: no sequence folders (no <code>sequence_*/metadata</code>).</p>")
    if rows:
        out.append(_table(["patient", "sequence", "planned frames", "simulated frames", "rendered frames",
                           "camera", "modalities", "rendered span (s)"], rows))
    conv = metadata_block()
    units = conv.pop("units")
    items = [("units", ", ".join(f"{k}: {v}" for k, v in sorted(units.items())))] + sorted(conv.items())
    items += [("depth", "planar z along the optical axis, metres; 0 = no surface hit"),
              ("optical flow", "forward t -> t+1, pixels (u right, v down); "
                               "invalid where occluded or leaving the image"),
              ("segmentation", "uint16 label = airway branch id + 1; 0 = no hit"),
              ("timestamps", "seconds from the sequence start")]
    out.append("<h3>Conventions</h3>")
    out.append("<dl class=\"conv\">" + "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in items) + "</dl>")
    return "\n".join(out)


# =========================================================================== section: thumbnails


def _thumb_column(mod: str, frames: list[dict], px: int) -> tuple[str, list[str]]:
    """(header html, one cell html per frame) of one modality column."""
    w_alt = lambda f: f"{mod} {f['name']}"  # noqa: E731

    def cells(images: list[np.ndarray], nearest: bool = False) -> list[str]:
        out = []
        for f, im in zip(frames, images):
            t = thumbnail(im, px, nearest)
            out.append(_img(png_uri(t), w_alt(f), t.shape[1], t.shape[0]))
        return out

    if mod in RGB_SOURCES:
        head = "RGB (8-bit sRGB)" if mod == "rgb" else "RGB with sensor noise"
        return _esc(head), cells([f[mod] for f in frames])
    if mod == "depth":
        vals = np.concatenate([f["depth"][f["depth"] > 0] for f in frames]) * 1e3
        if vals.size == 0:
            return "depth (no surface hit in these frames)", cells([np.zeros(f["depth"].shape + (3,), np.uint8)
                                                                    for f in frames])
        lo, hi = float(vals.min()), float(vals.max())
        bar = colour_bar("viridis")
        head = (f"depth, planar z (mm)<br>{_img(png_uri(bar), 'depth colour bar', bar.shape[1], bar.shape[0], 'bar')}"
                f'<br><span class="range">{lo:.1f} &larr; &rarr; {hi:.1f} mm</span>')
        return head, cells([colorize(f["depth"] * 1e3, lo, hi, "viridis", f["depth"] > 0) for f in frames])
    if mod == "relative_depth":
        bar = colour_bar("magma")
        bar_img = _img(png_uri(bar), "relative depth colour bar", bar.shape[1], bar.shape[0], "bar")
        head = (f"relative inverse depth<br>{bar_img}"
                '<br><span class="range">0 (farthest) &larr; &rarr; 1 (nearest)</span>')
        return head, cells([colorize(f["relative_depth"], 0.0, 1.0, "magma", f.get("valid")) for f in frames])
    if mod == "normals":
        head = ('surface normals, camera frame<br><span class="range">'
                "R, G, B = (n+1)/2 of x right, y down, z forward</span>")
        return head, cells([normals_rgb(f["normals"]) for f in frames])
    if mod == "flow":
        mags = np.concatenate([np.hypot(f["flow"][..., 0], f["flow"][..., 1])[f["flow_valid"]] for f in frames])
        mx = float(np.percentile(mags, 99)) if mags.size else 0.0
        mx = mx if mx > 1e-6 else 1.0
        wheel = flow_wheel(40)
        head = (f"optical flow t&rarr;t+1<br>{_img(png_uri(wheel), 'flow colour wheel', 40, 40, 'wheel')}"
                f'<br><span class="range">hue = direction (red = right), saturation = magnitude, full at '
                f"{mx:.2f} px; black = no valid flow (the last frame has none)</span>")
        return head, cells([flow_rgb(f["flow"], f["flow_valid"], mx) for f in frames])
    if mod == "segmentation":
        labels = sorted({int(x) for f in frames for x in np.unique(f["segmentation"]) if x > 0})
        head = (f'segmentation<br><span class="range">{len(labels)} branch label(s) in these frames '
                "(label = branch id + 1), one colour each</span>")
        return head, cells([labels_rgb(f["segmentation"]) for f in frames], nearest=True)
    raise ValueError(f"no thumbnail rule for modality {mod!r}")


def sequence_thumbnails(seq: Path, max_frames: int, px: int) -> str:
    """The thumbnail table of one rendered sequence (or a not-available line)."""
    from ..dataset.reader import SequenceReader

    try:
        probe = SequenceReader(seq)
        mods = [m for m in THUMB_MODALITIES if m in probe.modalities]
        if not mods:
            return _na(f"{seq.name}: no per-pixel modality recorded")
        r = SequenceReader(seq, mods)
        positions = pick_frames(len(r), max_frames)
        frames = [r.frame(i) for i in positions]
    except InputError as exc:
        return _na(str(exc))
    columns = [_thumb_column(m, frames, px) for m in mods]
    head = "<tr><th>frame</th>" + "".join(f"<th>{h}</th>" for h, _ in columns) + "</tr>"
    body = []
    for k, f in enumerate(frames):
        label = f"{_esc(f['name'])}<br>t = {f['timestamp']:.2f} s"
        body.append(f"<tr><td>{label}</td>" + "".join(f"<td>{c[k]}</td>" for _, c in columns) + "</tr>")
    i = r.intrinsics
    note = (f"<p>{len(r)} frames of {i['width']}x{i['height']} px; shown: "
            + ", ".join(f["name"] for f in frames) + f" (thumbnails at most {px} px).</p>")
    table = f'<table class="thumbs"><thead>{head}</thead><tbody>{"".join(body)}</tbody></table>'
    return note + f'<div class="scroll">{table}</div>'


def section_thumbnails(opts: ReportOptions, patients: list[Path]) -> str:
    from ..dataset.reader import is_sequence

    out = []
    for p in patients:
        for s in find_sequence_dirs(p):
            out.append(f"<h3>{_esc(p.name)} / {_esc(s.name)}</h3>")
            if not is_sequence(s):
                out.append(_na(f"{s.name} is not rendered (no metadata/render.json)"))
                continue
            out.append(sequence_thumbnails(s, opts.max_frames, opts.thumb_px))
    return "\n".join(out) if out else _na("no sequence folders")


# =========================================================================== section: real vs synthetic


def section_realism(opts: ReportOptions, patients: list[Path], n: int = 6) -> str:
    """Real frames beside ours (noisy RGB where present, else RGB), evenly spaced, with the realism statistics
    (:mod:`room_pipeline.realism`, 256 px, no noise spectrum)."""
    import cv2

    from .. import realism as R

    if opts.real_dir is None or not Path(opts.real_dir).is_dir():
        return _na("no real frames folder (room report --real-dir DIR; default ../shared/data/bronchoscopy_frames/"
                   "brea_depth)")
    ours: list[Path] = []
    for p in patients:
        for sq in find_sequence_dirs(p):
            for sub in (RGB_NOISY, "rgb"):
                fr = sorted(SequencePaths(sq).folder(sub).glob("frame_*.png"))
                if fr:
                    ours += fr
                    break
    if not ours:
        return _na("no rendered frames")
    try:
        real = R.frame_paths(opts.real_dir)
    except InputError as e:
        return _na(str(e))

    def row(paths: list[Path]) -> list[str]:
        sel = [paths[int(i)] for i in np.linspace(0, len(paths) - 1, min(n, len(paths)))]
        cells = []
        for q in sel:
            im = cv2.imread(str(q), cv2.IMREAD_COLOR)
            if im is None:
                cells.append(_na(f"{q.name} unreadable"))
                continue
            t = thumbnail(im[..., ::-1].copy(), opts.thumb_px)
            cells.append(_img(jpeg_uri(t), q.name, t.shape[1], t.shape[0]))
        return cells

    res = R.evaluate(opts.real_dir, None, n=60, size=256, noise=False, synth_paths=ours)
    vs, rr = res["real_vs_synth"], res.get("real_vs_real", {})
    stats = _table(["statistic", "ours vs real", "real vs real (halves)"],
                   [[k, _fmt(vs.get(k)), _fmt(rr.get(k))] for k in
                    ("dE76_mean_colour", "L_hist_emd", "radial_profile_mad", "gradient_hist_L1")]
                   + [["Lab mean (ours / real)", _fmt(res["synth"]["lab_mean"]), _fmt(res["real"]["lab_mean"])],
                      ["clipped fraction mean / worst frame (ours)",
                       f"{res['synth']['clipped_fraction_all_frames']:.4f} / "
                       f"{res['synth']['clipped_max_all_frames']:.4f}", _fmt(res["real"]["clipped_fraction"])]])
    return (f"<p>Top: real frames (<code>{_esc(_show(Path(opts.real_dir), opts.base))}</code>); bottom: ours "
            f"({len(ours)} frames). Statistics: <code>room realism</code>.</p>"
            + _table(["", *[str(i) for i in range(min(n, len(real), len(ours)))]],
                     [["real", *row(real)], ["ours", *row(ours)]], cls="thumbs", raw=True) + stats)


# =========================================================================== section: 3-D view


@dataclasses.dataclass
class Scene3D:
    """What one 3-D view draws (world RAS+, metres); None / empty = absent."""

    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    planned: np.ndarray | None = None          # (N, 3) planned camera positions
    simulated: np.ndarray | None = None        # (M, 3) simulated tip positions
    rendered: np.ndarray | None = None         # (K, 3) positions of the rendered cameras
    scopes: list = dataclasses.field(default_factory=list)   # (P, 3) backbone polylines
    tips: np.ndarray | None = None             # (S, 3) simulated tip positions at the scope frames
    scope_radius: float = 0.0025


def scope_backbones(trajectory: Mapping, simulation: Mapping, robot: Mapping, n_frames: int,
                    step_m: float = 1e-3) -> tuple[list[np.ndarray], np.ndarray, list[int], list[float]]:
    """Backbone polylines of the simulated scope at ``n_frames`` evenly spaced simulation frames.

    Reconstruction (the simulator's ``kinematic`` insertion model): the bending-segment base is
    the planned route's frame at arclength ``q3``, rolled by ``q2``; the shaft is the route from
    its start up to ``q3`` (sampled every ``step_m``); the bending segment is the constant-curvature
    arc of :func:`room_pipeline.robot.kinematics.fk` for ``q1``.  Joints are the recorded ``q_act``.

    Returns (polylines (P_i, 3) metres, simulated tip positions (S, 3), the frame indices, and per
    frame the distance (m) between the reconstructed tip and the simulated ``tip_pose``).
    Raises InputError when the inputs lack what the reconstruction needs.
    """
    from ..robot.kinematics import ScopeGeometry, fk
    from ..robot.pybullet_sim import Route

    if robot.get("insertion_model", "kinematic") != "kinematic":
        raise InputError(f"insertion model {robot.get('insertion_model')!r}: the shaft shape is not recorded "
                         "(only the kinematic model's shaft follows the planned route)")
    try:
        planned = pose_track_from_doc(trajectory, POSE_KEY[TRAJECTORY_JSON], TRAJECTORY_JSON)
        if planned.arclength is None:
            raise KeyError("arclength")
        k = robot.get("kinematics") or {}
        geometry = ScopeGeometry(l=float(k.get("bending_length", ScopeGeometry.l)),
                                 gamma=float(k.get("gamma", ScopeGeometry.gamma)),
                                 q1_max=float(k.get("q1_max", ScopeGeometry.q1_max)))
        sf = simulation["frames"]
        picks = pick_frames(len(sf), n_frames + 1)[1:] if n_frames > 0 and len(sf) > 1 else []
        picks = picks[-n_frames:] if n_frames else []
        qs = [np.asarray(sf[i]["q_act"], dtype=np.float64) for i in picks]
        tips = pose_track_from_doc(simulation, POSE_KEY[SIMULATION_JSON], SIMULATION_JSON).positions[picks]
    except (KeyError, TypeError, ValueError, IndexError, InputError) as exc:
        raise InputError(f"trajectory/simulation/robot_config lack what the scope drawing needs ({exc})") from None
    route = Route.from_trajectory(planned)
    lines, mismatch = [], []
    for q, tip in zip(qs, tips):
        s0 = float(route.s[0])
        shaft = [route.frame(s)[:3, 3] for s in np.arange(s0, q[2], step_m)] if q[2] > s0 else []
        base = route.frame(float(q[2]))
        c2, s2 = math.cos(q[1]), math.sin(q[1])
        base[:3, :3] = base[:3, :3] @ np.array([[c2, -s2, 0.0], [s2, c2, 0.0], [0.0, 0.0, 1.0]])
        ss = np.linspace(0.0, geometry.l, 25)
        arc = fk(np.array([q[0], 0.0, 0.0]), ss, geometry=geometry)
        bend = (base @ arc)[:, :3, 3]
        lines.append(np.vstack([np.reshape(shaft, (-1, 3)), bend]))
        mismatch.append(float(np.linalg.norm(bend[-1] - tip)))
    return lines, tips, picks, mismatch


def sequence_scene(seq: Path, mesh, scope_frames: int) -> tuple[Scene3D, list[str]]:
    """The 3-D scene of one sequence and the caption lines saying what is drawn (and what is not)."""
    sp = SequencePaths(seq)
    sc = Scene3D()
    notes = []
    if mesh is not None:
        sc.mesh_vertices, sc.mesh_faces = mesh.vertices, mesh.faces
    traj, why = _read_json(sp.trajectory)
    try:
        if traj is not None:
            sc.planned = pose_track_from_doc(traj, POSE_KEY[TRAJECTORY_JSON], sp.trajectory).positions
    except (KeyError, TypeError, ValueError, IndexError, InputError):
        traj, why = None, "trajectory.json has no 4x4 frame poses"
    if sc.planned is None:
        notes.append(f"planned trajectory not drawn: {why}")
    sim, why_s = _read_json(sp.simulation)
    try:
        if sim is not None:
            sc.simulated = pose_track_from_doc(sim, POSE_KEY[SIMULATION_JSON], sp.simulation).positions
    except (KeyError, TypeError, ValueError, IndexError, InputError):
        sim, why_s = None, "simulation.json has no tip poses"
    if sc.simulated is None:
        notes.append(f"simulated tip path not drawn: {why_s}")
    rend, _ = _read_json(sp.render_json)
    if isinstance(rend, dict) and rend.get("frames"):
        try:
            sc.rendered = pose_track_from_doc(rend, POSE_KEY[RENDER_JSON], sp.render_json).positions
        except (KeyError, TypeError, ValueError, IndexError, InputError):
            notes.append("rendered cameras not drawn: render.json frames lack 4x4 poses")
    if scope_frames and traj is not None and sim is not None:
        robot, why_r = _read_json(sp.robot_config)
        if robot is None:
            notes.append(f"scope not drawn: {why_r}")
        else:
            try:
                lines, tips, picks, mism = scope_backbones(traj, sim, robot, scope_frames)
                sc.scopes, sc.tips = lines, tips
                diam = (robot.get("scope") or {}).get("outer_diameter")
                if isinstance(diam, (int, float)) and diam > 0:
                    sc.scope_radius = 0.5 * float(diam)
                notes.append("scope (tube, outer diameter %.1f mm) at simulation frames %s; reconstructed "
                             "model tip vs simulated tip: %s mm" % (2e3 * sc.scope_radius,
                                                                   ", ".join(map(str, picks)),
                                                                   ", ".join(f"{1e3 * m:.2f}" for m in mism)))
            except InputError as exc:
                notes.append(f"scope not drawn: {exc}")
    elif scope_frames:
        notes.append("scope not drawn: it needs trajectory.json and simulation.json")
    return sc, notes


def _bounds(points: Sequence[np.ndarray], pad: float) -> tuple[float, ...]:
    P = np.vstack([np.reshape(p, (-1, 3)) for p in points])
    lo, hi = P.min(0) - pad, P.max(0) + pad
    return (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])


def _path_points(sc: Scene3D) -> list[np.ndarray]:
    pts = [p for p in (sc.planned, sc.simulated, sc.rendered) if p is not None and len(p)]
    return pts + [s for s in sc.scopes if len(s)]


def _closeup_bounds(sc: Scene3D, radius: float = 0.03, pad: float = 0.004) -> tuple[float, ...]:
    """Bounds of the drawn points within ``radius`` (m) of the distal end (the last simulated tip,
    else the last planned or rendered position), padded by ``pad``."""
    ends = [p for p in (sc.tips, sc.simulated, sc.planned, sc.rendered) if p is not None and len(p)]
    end = np.asarray(ends[0])[-1]
    P = np.vstack([np.reshape(p, (-1, 3)) for p in _path_points(sc)])
    near = P[np.linalg.norm(P - end, axis=1) <= radius]
    return _bounds([near if len(near) else end[None]], pad)


def render_pyvista(sc: Scene3D, size: tuple[int, int], closeup: bool) -> np.ndarray:
    """Off-screen pyvista screenshot (H, W, 3) uint8; anterior view (camera on +y, up +z, so the
    patient's right is on the image left, as in radiology).  Raises whatever VTK raises."""
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    # without a display VTK tries X first and logs a warning before it falls back to EGL / OSMesa
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    path = _path_points(sc)
    ext = np.ptp(np.vstack([sc.mesh_vertices] + path) if sc.mesh_vertices is not None else np.vstack(path), axis=0)
    diag = float(np.linalg.norm(ext)) or 0.1
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        pl.set_background("white")
        # translucent airway and scope: depth peeling, which needs multisampling off (SSAA instead;
        # VTK's FXAA is not supported by its EGL / OSMesa builds)
        pl.disable_anti_aliasing()
        pl.enable_depth_peeling(number_of_peels=8, occlusion_ratio=0.0)
        pl.enable_anti_aliasing("ssaa")
        if sc.mesh_vertices is not None:
            faces = np.hstack([np.full((len(sc.mesh_faces), 1), 3), sc.mesh_faces]).ravel()
            pl.add_mesh(pv.PolyData(sc.mesh_vertices, faces), color=COLOURS["airway"], opacity=0.22,
                        smooth_shading=True)
        r_line = (0.00035 if closeup else 0.003 * diag)

        def polyline(P):   # one polyline cell (not a cell per segment, whose tubes would each be capped)
            P = np.asarray(P, dtype=np.float64)
            return pv.PolyData(P, lines=np.concatenate([[len(P)], np.arange(len(P))]))

        def line(P, colour, r):
            if P is not None and len(P) >= 2:
                pl.add_mesh(polyline(P).tube(radius=r, n_sides=10), color=colour)

        line(sc.planned, COLOURS["planned"], r_line)
        line(sc.simulated, COLOURS["simulated"], r_line)
        if sc.rendered is not None and len(sc.rendered):
            pl.add_mesh(pv.PolyData(np.asarray(sc.rendered)), color=COLOURS["rendered"],
                        point_size=7 if closeup else 5, render_points_as_spheres=True)
        if closeup:   # the scope at its true diameter, translucent so the paths inside stay visible
            for s in sc.scopes:
                if len(s) >= 2:
                    pl.add_mesh(polyline(s).tube(radius=sc.scope_radius, n_sides=20),
                                color=COLOURS["scope"], opacity=0.35)
            for t in (sc.tips if sc.tips is not None else []):
                pl.add_mesh(pv.Sphere(radius=0.5 * sc.scope_radius, center=tuple(t)), color=COLOURS["tip"])
        if closeup:
            b = _closeup_bounds(sc)
        else:
            b = _bounds([sc.mesh_vertices], 0.0) if sc.mesh_vertices is not None else _bounds(path, 0.004)
        c = np.array([(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2])
        pl.camera.focal_point = tuple(c)
        pl.camera.position = tuple(c + np.array([0.0, 1.0, 0.0]))
        pl.camera.up = (0.0, 0.0, 1.0)
        pl.reset_camera(bounds=b)
        if not closeup:
            pl.camera.zoom(1.15)
        img = pl.screenshot(return_img=True)
    finally:
        pl.close()
    return np.ascontiguousarray(np.asarray(img)[..., :3], dtype=np.uint8)


def render_matplotlib(sc: Scene3D, size: tuple[int, int], closeup: bool) -> np.ndarray:
    """The matplotlib 3-D fallback (mesh as a light point cloud), same content and viewpoint."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    path = _path_points(sc)
    if sc.mesh_vertices is not None:
        V = sc.mesh_vertices
        if closeup:
            b = _closeup_bounds(sc, pad=0.008)
            V = V[(V[:, 0] >= b[0]) & (V[:, 0] <= b[1]) & (V[:, 1] >= b[2]) & (V[:, 1] <= b[3])
                  & (V[:, 2] >= b[4]) & (V[:, 2] <= b[5])]
        V = V[:: max(1, len(V) // 15000)]
        ax.scatter(V[:, 0], V[:, 1], V[:, 2], s=0.3, c=[COLOURS["airway"]], alpha=0.25, linewidths=0)
    for P, key in ((sc.planned, "planned"), (sc.simulated, "simulated")):
        if P is not None and len(P):
            ax.plot(P[:, 0], P[:, 1], P[:, 2], color=COLOURS[key], lw=1.5)
    if sc.rendered is not None and len(sc.rendered):
        R = sc.rendered
        ax.scatter(R[:, 0], R[:, 1], R[:, 2], s=8, c=[COLOURS["rendered"]])
    if closeup:
        for s in sc.scopes:
            ax.plot(s[:, 0], s[:, 1], s[:, 2], color=COLOURS["scope"], lw=4, alpha=0.6)
        if sc.tips is not None and len(sc.tips):
            ax.scatter(sc.tips[:, 0], sc.tips[:, 1], sc.tips[:, 2], s=25, c=[COLOURS["tip"]])
    if closeup:
        b = _closeup_bounds(sc)
    else:
        b = _bounds([sc.mesh_vertices], 0) if sc.mesh_vertices is not None else _bounds(path, 0.004)
    half = max(b[1] - b[0], b[3] - b[2], b[5] - b[4]) / 2
    c = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
    ax.view_init(elev=0, azim=90)   # from +y (anterior), z up
    ax.set_xlabel("x (m, R)")
    ax.set_zlabel("z (m, S)")
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _legend(sc: Scene3D) -> str:
    items = [("airway", "airway lumen (semi-transparent)", sc.mesh_vertices is not None),
             ("planned", "planned trajectory", sc.planned is not None),
             ("simulated", "simulated tip path", sc.simulated is not None),
             ("rendered", "rendered cameras", sc.rendered is not None),
             ("scope", "scope backbone (tube)", bool(sc.scopes)),
             ("tip", "simulated tip at those frames", bool(sc.scopes))]
    sw = lambda c: "#%02x%02x%02x" % tuple(round(255 * x) for x in c)  # noqa: E731
    return '<p class="legend">' + " ".join(
        f'<span class="sw" style="background:{sw(COLOURS[k])}"></span>{_esc(t)}' for k, t, on in items if on) + "</p>"


def section_view3d(opts: ReportOptions, patients: list[Path]) -> str:
    from ..io.mesh import read_obj
    from ..paths import PatientPaths

    out = []
    pyvista_error: str | None = None if opts.use_pyvista else "disabled (use_pyvista=False)"
    for p in patients:
        seqs = find_sequence_dirs(p)
        if not seqs:
            continue
        mesh_path = PatientPaths(p.parent, p.name).mesh
        mesh = None
        try:
            mesh = read_obj(mesh_path) if mesh_path.is_file() else None
        except InputError as exc:
            out.append(_na(str(exc)))
        for s in seqs:
            out.append(f"<h3>{_esc(p.name)} / {_esc(s.name)}</h3>")
            sc, notes = sequence_scene(s, mesh, opts.scope_frames)
            if mesh is None:
                notes.insert(0, f"airway mesh not drawn: no {_show(mesh_path, opts.base)}")
            if not _path_points(sc):
                out.append(_na(f"{s.name}: no trajectory, simulation or rendered poses to draw"))
                continue
            images = []
            for closeup, title in ((False, "overview (paths only)"),
                                   (True, "close-up: distal 30 mm, with the scope")):
                img, how = None, ""
                if pyvista_error is None:
                    try:
                        img = render_pyvista(sc, opts.view_size, closeup)
                        how = "pyvista (VTK, off-screen)"
                    except Exception as exc:  # any VTK/OpenGL failure: fall back, and say so
                        pyvista_error = f"{exc.__class__.__name__}: {exc}".splitlines()[0][:200]
                if img is None:
                    img = render_matplotlib(sc, opts.view_size, closeup)
                    how = f"matplotlib 3-D fallback (pyvista off-screen rendering unavailable: {pyvista_error})"
                images.append((title, img, how))
            figs = "".join(
                f'<figure>{_img(jpeg_uri(im), f"3-D {title} {s.name}", im.shape[1], im.shape[0])}'
                f"<figcaption>{_esc(title)}; drawn by {_esc(how)}</figcaption></figure>" for title, im, how in images)
            out.append(f'<div class="views">{figs}</div>')
            out.append(_legend(sc))
            out.append("<p class=\"note\">Anterior view (patient's right on the image left, superior up). "
                       + " ".join(_esc(n[0].upper() + n[1:] + ".") for n in notes) + "</p>")
    return "\n".join(out) if out else _na("no sequence folders with metadata")


# =========================================================================== section: metrics


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
    parts = [f"{k} = {_fmt(v)}" for k, v in items[:n]]
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
        out.append(f"<h3>{_esc(p.name)}</h3>")
        files = sorted(f for f in mdir.glob("*.json") if not is_timing_file(f)) if mdir.is_dir() else []
        if not files:
            out.append(_na(f"no {p.name}/metrics/*.json"))
            continue
        rows, total = [], 0.0
        for f in files:
            doc, why = _read_json(f)
            if not isinstance(doc, Mapping):
                rows.append([_esc(f.stem), "-", "-", _esc(f"not available: {why or 'not a JSON object'}"), ""])
                continue
            tim, _ = _read_json(timing_path(f))        # the stage's timings (absent in older outputs)
            if isinstance(tim, Mapping):
                doc = merge_timings(doc, {k: v for k, v in tim.items() if k != "units"})
            wt, rss = doc.get("wall_time_s"), doc.get("peak_rss_mb")
            if isinstance(wt, (int, float)) and not isinstance(wt, bool):
                total += float(wt)
            leaves = flatten(doc)
            details = ("<details><summary>all %d values</summary>" % len(leaves)
                       + _table(["key", "value"], [(k, _fmt(v)) for k, v in leaves], cls="kv") + "</details>")
            rows.append([_esc(f.stem), _esc(_fmt(wt)), _esc(_fmt(rss)), _esc(_headline(doc)), details])
        rows.append(["<b>total</b>", f"<b>{total:.1f}</b>", "", "sum of the stages' wall times", ""])
        out.append(_table(["stage", "wall time (s)", "peak RSS (MB)", "headline numbers", "details"], rows,
                          raw=True))
    out.append('<p class="note">Wall times and memory depend on the machine and its load when the stage ran.</p>')
    return "\n".join(out) if patients else _na("no patients")


# =========================================================================== section: benchmarks


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
        return _na(f"no benchmark results folder ({_show(d, opts.base) if d else 'none given'})")
    d = Path(d)
    out, figs = [], []
    for stem, builder in BENCHMARK_PLOTS:
        f = d / f"{stem}.json"
        doc, why = _read_json(f)
        if doc is None:
            figs.append(f'<figure class="plot">{_na(f"{stem}: {why}")}</figure>')
            continue
        try:
            plot = builder(doc)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            figs.append(f'<figure class="plot">{_na(f"{stem}.json has an unexpected structure ({exc!r})")}</figure>')
            continue
        uri = _uri(plot_png(plot), "image/png")
        cap = f"{stem}.json" + (f"; {plot.note}" if plot.note else "")
        figs.append(f'<figure class="plot">{_img(uri, plot.title, 560, 360)}'
                    f"<figcaption>{_esc(cap)}</figcaption></figure>")
    out.append(f'<div class="plots">{"".join(figs)}</div>')
    mds = sorted(d.glob("*.md"))
    if mds:
        out.append("<h3>All benchmark results</h3>")
        out.append(_table(["file", "title"], [(m.name, _md_title(m)) for m in mds]))
    out.append('<p class="note">Timings were measured on shared machines; each result file states its command '
               "and the machine load.</p>")
    return "\n".join(out)


# =========================================================================== section: paper tables


def _inline_md(text: str) -> str:
    s = _esc(text)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)


def _cells(line: str) -> list[str]:
    s = line.strip()
    if s.startswith("|"):
        s = s[1:]
    if s.endswith("|"):
        s = s[:-1]
    return [c.strip() for c in s.split("|")]


def markdown_to_html(text: str) -> str:
    """The Markdown subset of the generated tables: headings, pipe tables, bullet lists, paragraphs."""
    lines = text.splitlines()
    out, i = [], 0
    sep = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)*\|?\s*$")
    while i < len(lines):
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        m = re.match(r"^(#{1,6})\s+(.*)$", line)
        if m:
            level = min(6, len(m.group(1)) + 2)
            out.append(f"<h{level}>{_inline_md(m.group(2))}</h{level}>")
            i += 1
        elif line.lstrip().startswith("|") and i + 1 < len(lines) and sep.match(lines[i + 1]):
            head = _cells(line)
            align = ["right" if c.strip().endswith(":") else "left" for c in _cells(lines[i + 1])]
            i += 2
            rows = []
            while i < len(lines) and lines[i].lstrip().startswith("|"):
                rows.append(_cells(lines[i]))
                i += 1
            right = [a == "right" for a in align]
            st = lambda k: ' style="text-align:right"' if k < len(right) and right[k] else ""  # noqa: E731
            out.append('<table class="data"><thead><tr>' + "".join(
                f"<th{st(k)}>{_inline_md(h)}</th>" for k, h in enumerate(head)) + "</tr></thead><tbody>" + "".join(
                "<tr>" + "".join(f"<td{st(k)}>{_inline_md(c)}</td>" for k, c in enumerate(r)) + "</tr>"
                for r in rows) + "</tbody></table>")
        elif re.match(r"^\s*[-*]\s+", line):
            items = []
            while i < len(lines) and re.match(r"^\s*[-*]\s+", lines[i]):
                items.append(re.sub(r"^\s*[-*]\s+", "", lines[i]))
                i += 1
            out.append("<ul>" + "".join(f"<li>{_inline_md(t)}</li>" for t in items) + "</ul>")
        else:
            para = []
            while i < len(lines) and lines[i].strip() and not lines[i].lstrip().startswith(("|", "#")) \
                    and not re.match(r"^\s*[-*]\s+", lines[i]):
                para.append(lines[i].strip())
                i += 1
            if not para:  # a lone table row without its separator: show it as text
                para, i = [line.strip()], i + 1
            out.append(f"<p>{_inline_md(' '.join(para))}</p>")
    return "\n".join(out)


def section_tables(opts: ReportOptions) -> str:
    import csv

    d = opts.tables_dir
    hint = "(the `tables` stage writes them: room stage tables --patient all)"
    if d is None or not Path(d).is_dir():
        return _na(f"not generated yet: no folder {_show(d, opts.base) if d else '(none given)'} {hint}")
    d = Path(d)
    mds = sorted(d.glob("table_*.md"))
    stems = {m.stem for m in mds}
    csvs = [c for c in sorted(d.glob("table_*.csv")) if c.stem not in stems]
    if not mds and not csvs:
        return _na(f"not generated yet: no table_*.md or table_*.csv in {_show(d, opts.base)} {hint}")
    out = []
    for m in mds:
        out.append(f'<div class="papertable"><p class="src">{_esc(m.name)}</p>'
                   f"{markdown_to_html(m.read_text(encoding='utf-8'))}</div>")
    for c in csvs:
        rows = list(csv.reader(io.StringIO(c.read_text(encoding="utf-8"))))
        body = _table(rows[0], rows[1:]) if rows else _na(f"{c.name} is empty")
        out.append(f'<div class="papertable"><p class="src">{_esc(c.name)}</p>{body}</div>')
    return "\n".join(out)


# =========================================================================== the page

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1240px;
padding:0 18px 40px;color:#1d1f23;background:#fff}
h1{font-size:24px;margin:22px 0 4px}h2{font-size:19px;margin:34px 0 8px;border-bottom:2px solid #d9dde3;
padding-bottom:4px}h3{font-size:15px;margin:20px 0 6px}nav a{margin-right:14px}
table{border-collapse:collapse;margin:6px 0 12px}th,td{border:1px solid #d9dde3;padding:3px 7px;
vertical-align:top;text-align:left}th{background:#f3f5f8;font-weight:600}
table.data td,table.kv td{font-variant-numeric:tabular-nums}table.kv{font-size:12px}
table.thumbs th{font-weight:500;font-size:12px;max-width:170px}table.thumbs td{padding:2px;font-size:12px}
table.thumbs img{display:block;image-rendering:auto}.scroll{overflow-x:auto}
img.bar{width:160px;height:10px;margin-top:3px}.range{color:#555;font-size:11px}
.na{color:#8a4b00;background:#fff6e8;border-left:3px solid #e0a040;padding:3px 8px}
.note{color:#555;font-size:12px}.legend .sw{display:inline-block;width:12px;height:12px;margin:0 4px 0 12px;
vertical-align:-1px;border:1px solid #999}.views,.plots{display:flex;flex-wrap:wrap;gap:12px}
figure{margin:0}figcaption{font-size:12px;color:#555;max-width:760px}
dl.conv{display:grid;grid-template-columns:max-content 1fr;gap:2px 14px}dl.conv dt{font-weight:600}
dl.conv dd{margin:0}.papertable .src{color:#777;font-size:12px;margin-bottom:0}code{background:#f3f5f8;padding:0 3px}
details summary{cursor:pointer;color:#3558a8}footer{margin-top:40px;color:#777;font-size:12px}
"""

_SCRIPT = """window.addEventListener("load",function(){var im=document.images,ok=0;
for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0){ok++;}}
document.body.setAttribute("data-images-loaded",ok+"/"+im.length);});"""

_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"


def build_report(opts: ReportOptions) -> str:
    """The report page (HTML text) for ``opts`` (see the module docstring)."""
    from .. import __version__

    root = Path(opts.output_dir)
    if not root.is_dir():
        raise InputError(f"dataset folder not found (or not a folder): {root}")
    patients = find_patients(root)
    bodies = {
        "summary": section_summary(opts, patients),
        "thumbnails": section_thumbnails(opts, patients) if patients else _na("no patients"),
        "realism": section_realism(opts, patients),
        "view3d": section_view3d(opts, patients) if patients else _na("no patients"),
        "metrics": section_metrics(opts, patients),
        "benchmarks": section_benchmarks(opts),
        "tables": section_tables(opts),
    }
    name = _show(root, opts.base)
    nav = "".join(f'<a href="#{sid}">{_esc(title)}</a>' for sid, title in SECTIONS)
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f'<meta http-equiv="Content-Security-Policy" content="{_CSP}">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>ROOM dataset report: {_esc(name)}</title><style>{_CSS}</style></head>",
             '<body data-images-loaded="pending">',
             f"<header><h1>ROOM dataset report</h1><p>Dataset <code>{_esc(name)}</code>; "
             f"room-pipeline {_esc(__version__)}.</p><nav>{nav}</nav></header>"]
    for sid, title in SECTIONS:
        parts.append(f'<section id="{sid}"><h2>{_esc(title)}</h2>\n{bodies[sid]}\n</section>')
    parts.append("<footer>Written by <code>room report</code>; self-contained (images are embedded data URIs; "
                 "no network access). Same inputs give the same file: it carries no time stamp.</footer>")
    parts.append(f"<script>{_SCRIPT}</script></body></html>")
    return "\n".join(parts) + "\n"


def write_report(opts: ReportOptions, out: str | os.PathLike | None = None) -> Path:
    """Build the report and write it atomically to ``out`` (default ``<output_dir>/report.html``)."""
    from ..io.atomic import write_text

    target = Path(out) if out is not None else Path(opts.output_dir) / "report.html"
    write_text(target, build_report(opts))
    return target


# =========================================================================== command line


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of ``room report`` (shared by :func:`main` and ``room_pipeline.cli``)."""
    parser.add_argument("--output-dir", help="dataset root (default: output_dir of the composed conf/)")
    parser.add_argument("--out", help="HTML file to write (default: <output_dir>/report.html)")
    parser.add_argument("--max-frames", type=int, default=4, help="thumbnail frames per sequence (default 4)")
    parser.add_argument("--benchmarks-dir", help="benchmark results (default: <project>/benchmarks/results)")
    parser.add_argument("--tables-dir", help="paper tables (default: evaluate.tables.output_dir, i.e. reports/)")
    parser.add_argument("--real-dir", help="real bronchoscopy frames shown beside ours "
                                           "(default: ../shared/data/bronchoscopy_frames/brea_depth when present)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the composed config (key=value)")


def options_from_args(args: argparse.Namespace) -> tuple[ReportOptions, Path]:
    """Resolve the defaults: paths from the project's conf/ (relative ones against the project folder)."""
    from ..config.compose import find_conf_dir

    try:
        project = find_conf_dir().parent
    except ConfigError:
        project = None
    overrides = list(getattr(args, "overrides", None) or [])
    cfg = None
    if project is not None and (args.output_dir is None or args.tables_dir is None or overrides):
        from ..config.compose import compose

        cfg = compose(overrides)
    elif overrides:
        raise ConfigError("config overrides given but no conf/config.yaml found in this folder or its parents")
    base = project or Path.cwd()

    def under(p: str | os.PathLike) -> Path:
        p = Path(p)
        return p if p.is_absolute() else base / p

    if args.output_dir is not None:
        output_dir = Path(args.output_dir)
    elif cfg is not None and cfg.get("output_dir"):
        output_dir = under(str(cfg.output_dir))
    else:
        raise ConfigError("no --output-dir given and no conf/config.yaml in this folder or its parents")
    if args.tables_dir is not None:
        tables = Path(args.tables_dir)
    else:
        sub = None
        if cfg is not None:
            from omegaconf import OmegaConf

            sub = OmegaConf.select(cfg, "evaluate.tables.output_dir", default=None)
        tables = under(str(sub or "reports"))
    bench = Path(args.benchmarks_dir) if args.benchmarks_dir is not None else under("benchmarks/results")
    real = (Path(args.real_dir) if getattr(args, "real_dir", None)
            else base.parent / "shared" / "data" / "bronchoscopy_frames" / "brea_depth")
    opts = ReportOptions(output_dir=output_dir, benchmarks_dir=bench, tables_dir=tables,
                         max_frames=args.max_frames, base=base, real_dir=real if real.is_dir() else None)
    out = Path(args.out) if args.out else output_dir / "report.html"
    return opts, out


def run_args(args: argparse.Namespace) -> int:
    """``room report`` with parsed arguments; prints what it wrote."""
    opts, out = options_from_args(args)
    path = write_report(opts, out)
    text = path.read_text(encoding="utf-8")
    n_img = text.count("<img ")
    n_na = text.count('class="na"')
    print(f"room report: wrote {path} ({len(text.encode('utf-8')) / 1e6:.2f} MB, {n_img} images, "
          f"{n_na} 'not available' notes)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``room report [--output-dir DIR] [--out FILE] [--max-frames N] [--benchmarks-dir DIR] [--tables-dir DIR]``."""
    parser = argparse.ArgumentParser(prog="room report", description="write the self-contained HTML dataset report")
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_args(args)
    except RoomError as exc:
        print(f"room: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
