"""The whole page: CSS, the inline load-check script, the Content-Security-Policy, :func:`build_report`."""
from __future__ import annotations

import html
import os
from pathlib import Path

from ..errors import InputError
from .common import esc, na, show_path
from .discovery import find_patients
from .draw3d import section_view3d
from .metrics import section_metrics
from .navigation import NAVIGATION_SECTION, section_navigation
from .options import ReportOptions, SECTIONS
from .plots import section_benchmarks
from .sections import section_realism, section_summary, section_thumbnails
from .tables import section_tables


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
        "thumbnails": section_thumbnails(opts, patients) if patients else na("no patients"),
        "realism": section_realism(opts, patients),
        "view3d": section_view3d(opts, patients) if patients else na("no patients"),
        "metrics": section_metrics(opts, patients),
        "benchmarks": section_benchmarks(opts),
        "tables": section_tables(opts),
    }
    sections = list(SECTIONS)
    demo = section_navigation(opts)          # only for a dataset with `room navigate demo` output
    if demo is not None:
        sections.insert([sid for sid, _ in sections].index("view3d") + 1, NAVIGATION_SECTION)
        bodies[NAVIGATION_SECTION[0]] = demo
    name = show_path(root, opts.base)
    nav = "".join(f'<a href="#{sid}">{esc(title)}</a>' for sid, title in sections)
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f'<meta http-equiv="Content-Security-Policy" content="{_CSP}">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>ROOM dataset report: {esc(name)}</title><style>{_CSS}</style></head>",
             '<body data-images-loaded="pending">',
             f"<header><h1>ROOM dataset report</h1><p>Dataset <code>{esc(name)}</code>; "
             f"room-pipeline {esc(__version__)}.</p><nav>{nav}</nav></header>"]
    for sid, title in sections:
        parts.append(f'<section id="{sid}"><h2>{esc(title)}</h2>\n{bodies[sid]}\n</section>')
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
