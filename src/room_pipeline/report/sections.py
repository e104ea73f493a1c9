"""The page's text and image sections: dataset summary, modality thumbnails, real vs synthetic frames."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..catalog import RGB_NOISY, RGB_SOURCES, SequencePaths
from ..errors import InputError
from .colour import colorize, colour_bar, flow_rgb, flow_wheel, labels_rgb, normals_rgb, pick_frames, thumbnail
from .common import esc, fmt, img_tag, na, read_json, show_path, html_table, jpeg_uri, png_uri
from .discovery import find_sequence_dirs
from .options import ReportOptions, THUMB_MODALITIES

# =========================================================================== section: summary


def _sequence_row(seq: Path) -> list[str]:
    """A rendered sequence's summary row (its planned and simulated frame counts too)."""
    from ..dataset.reader import SequenceReader

    traj, why_t = read_json(SequencePaths(seq).trajectory)
    sim, why_s = read_json(SequencePaths(seq).simulation)
    has = lambda doc: isinstance(doc, dict) and bool(doc.get("frames"))  # noqa: E731
    planned = f"{len(traj['frames'])}" if has(traj) else f"- ({why_t or 'no frames'})"
    if isinstance(traj, dict) and isinstance(traj.get("summary"), dict) and "length_m" in traj["summary"]:
        planned += f", {1e3 * float(traj['summary']['length_m']):.1f} mm"
    tgt = traj.get("target") if isinstance(traj, dict) else None
    if isinstance(tgt, dict) and "stop_distance" in tgt:  # how far from the target the scope stopped, and why
        planned += f"; stopped {1e3 * float(tgt['stop_distance']):.1f} mm from the target ({tgt.get('stop_reason', '?')})"
    simulated = f"{len(sim['frames'])}" if has(sim) else f"- ({why_s or 'no frames'})"
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


def section_summary(opts: ReportOptions, patients: list[Path]) -> str:
    from ..conventions import metadata_block

    if not patients:
        return na(f"no patient folders in {show_path(opts.output_dir, opts.base)}")
    rows, counts = [], []
    for p in patients:
        seqs = find_sequence_dirs(p)
        counts.append(len(seqs))
        rows += [_sequence_row(s) for s in seqs]
    out = [f"<p>{len(patients)} patient(s), {sum(counts)} rendered sequence(s), "
           f"in <code>{esc(show_path(opts.output_dir, opts.base))}</code>.</p>"]
    for p, n in zip(patients, counts):
        if n == 0:
            out.append(f"<p>{esc(p.name)}: no rendered sequence (no <code>sequence_*/metadata/render.json</code>)."
                       "</p>")
    if rows:
        out.append(html_table(["patient", "sequence", "planned frames", "simulated frames", "rendered frames",
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
    out.append("<dl class=\"conv\">" + "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in items) + "</dl>")
    return "\n".join(out)


# =========================================================================== section: thumbnails


def _thumb_column(mod: str, frames: list[dict], px: int) -> tuple[str, list[str]]:
    """(header html, one cell html per frame) of one modality column."""
    w_alt = lambda f: f"{mod} {f['name']}"  # noqa: E731

    def cells(images: list[np.ndarray], nearest: bool = False) -> list[str]:
        out = []
        for f, im in zip(frames, images):
            t = thumbnail(im, px, nearest)
            out.append(img_tag(png_uri(t), w_alt(f), t.shape[1], t.shape[0]))
        return out

    if mod in RGB_SOURCES:
        head = "RGB (8-bit sRGB)" if mod == "rgb" else "RGB with sensor noise"
        return esc(head), cells([f[mod] for f in frames])
    if mod == "depth":
        vals = np.concatenate([f["depth"][f["depth"] > 0] for f in frames]) * 1e3
        if vals.size == 0:
            return "depth (no surface hit in these frames)", cells([np.zeros(f["depth"].shape + (3,), np.uint8)
                                                                    for f in frames])
        lo, hi = float(vals.min()), float(vals.max())
        bar = colour_bar("viridis")
        head = (f"depth, planar z (mm)<br>{img_tag(png_uri(bar), 'depth colour bar', bar.shape[1], bar.shape[0], 'bar')}"
                f'<br><span class="range">{lo:.1f} &larr; &rarr; {hi:.1f} mm</span>')
        return head, cells([colorize(f["depth"] * 1e3, lo, hi, "viridis", f["depth"] > 0) for f in frames])
    if mod == "relative_depth":
        bar = colour_bar("magma")
        bar_img = img_tag(png_uri(bar), "relative depth colour bar", bar.shape[1], bar.shape[0], "bar")
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
        head = (f"optical flow t&rarr;t+1<br>{img_tag(png_uri(wheel), 'flow colour wheel', 40, 40, 'wheel')}"
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
            return na(f"{seq.name}: no per-pixel modality recorded")
        r = SequenceReader(seq, mods)
        positions = pick_frames(len(r), max_frames)
        frames = [r.frame(i) for i in positions]
    except InputError as exc:
        return na(str(exc))
    columns = [_thumb_column(m, frames, px) for m in mods]
    head = "<tr><th>frame</th>" + "".join(f"<th>{h}</th>" for h, _ in columns) + "</tr>"
    body = []
    for k, f in enumerate(frames):
        label = f"{esc(f['name'])}<br>t = {f['timestamp']:.2f} s"
        body.append(f"<tr><td>{label}</td>" + "".join(f"<td>{c[k]}</td>" for _, c in columns) + "</tr>")
    i = r.intrinsics
    note = (f"<p>{len(r)} frames of {i['width']}x{i['height']} px; shown: "
            + ", ".join(f["name"] for f in frames) + f" (thumbnails at most {px} px).</p>")
    table = f'<table class="thumbs"><thead>{head}</thead><tbody>{"".join(body)}</tbody></table>'
    return note + f'<div class="scroll">{table}</div>'


def section_thumbnails(opts: ReportOptions, patients: list[Path]) -> str:
    out = []
    for p in patients:
        for s in find_sequence_dirs(p):
            out.append(f"<h3>{esc(p.name)} / {esc(s.name)}</h3>")
            out.append(sequence_thumbnails(s, opts.max_frames, opts.thumb_px))
    return "\n".join(out) if out else na("no rendered sequence")


# =========================================================================== section: real vs synthetic


def section_realism(opts: ReportOptions, patients: list[Path], n: int = 6) -> str:
    """Real frames beside ours (noisy RGB where present, else RGB), evenly spaced, with the realism statistics
    (:mod:`room_pipeline.realism`, 256 px, no noise spectrum)."""
    import cv2

    from .. import realism as R

    if opts.real_dir is None or not Path(opts.real_dir).is_dir():
        return na("no real frames folder (room report --real-dir DIR; default ../shared/data/bronchoscopy_frames/"
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
        return na("no rendered frames")
    try:
        real = R.frame_paths(opts.real_dir)
    except InputError as e:
        return na(str(e))

    def row(paths: list[Path]) -> list[str]:
        sel = [paths[int(i)] for i in np.linspace(0, len(paths) - 1, min(n, len(paths)))]
        cells = []
        for q in sel:
            im = cv2.imread(str(q), cv2.IMREAD_COLOR)
            if im is None:
                cells.append(na(f"{q.name} unreadable"))
                continue
            t = thumbnail(im[..., ::-1].copy(), opts.thumb_px)
            cells.append(img_tag(jpeg_uri(t), q.name, t.shape[1], t.shape[0]))
        return cells

    res = R.evaluate(opts.real_dir, None, n=60, size=256, noise=False, synth_paths=ours)
    vs, rr = res["real_vs_synth"], res.get("real_vs_real", {})
    stats = html_table(["statistic", "ours vs real", "real vs real (halves)"],
                   [[k, fmt(vs.get(k)), fmt(rr.get(k))] for k in
                    ("dE76_mean_colour", "L_hist_emd", "radial_profile_mad", "gradient_hist_L1")]
                   + [["Lab mean (ours / real)", fmt(res["synth"]["lab_mean"]), fmt(res["real"]["lab_mean"])],
                      ["clipped fraction mean / worst frame (ours)",
                       f"{res['synth']['clipped_fraction_all_frames']:.4f} / "
                       f"{res['synth']['clipped_max_all_frames']:.4f}", fmt(res["real"]["clipped_fraction"])]])
    return (f"<p>Top: real frames (<code>{esc(show_path(Path(opts.real_dir), opts.base))}</code>); bottom: ours "
            f"({len(ours)} frames). Statistics: <code>room realism</code>.</p>"
            + html_table(["", *[str(i) for i in range(min(n, len(real), len(ours)))]],
                     [["real", *row(real)], ["ours", *row(ours)]], cls="thumbs", raw=True) + stats)
