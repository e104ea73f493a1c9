"""The ``tables`` section: the paper tables the `tables` stage wrote, Markdown rendered to HTML."""
from __future__ import annotations

import io
from pathlib import Path

from .common import esc, na, show_path, html_table
from .options import ReportOptions


def _markdown():
    from markdown_it import MarkdownIt

    # CommonMark with pipe tables; raw HTML in the text is escaped, never passed through
    return MarkdownIt("commonmark", {"html": False}).enable("table")


def markdown_to_html(text: str) -> str:
    """Markdown (CommonMark + pipe tables, by markdown-it-py) as HTML for the page: headings move down two
    levels (a table's ``#`` is an ``<h3>`` under the section's ``<h2>``) and tables get ``class="data"``."""
    md = _markdown()
    tokens = md.parse(text)
    for t in tokens:
        if t.type in ("heading_open", "heading_close"):
            t.tag = f"h{min(6, int(t.tag[1:]) + 2)}"
        elif t.type == "table_open":
            t.attrSet("class", "data")
    return md.renderer.render(tokens, md.options, {}).strip()


def section_tables(opts: ReportOptions) -> str:
    import csv

    d = opts.tables_dir
    hint = "(the `tables` stage writes them: room stage tables --patient all)"
    if d is None or not Path(d).is_dir():
        return na(f"not generated yet: no folder {show_path(d, opts.base) if d else '(none given)'} {hint}")
    d = Path(d)
    mds = sorted(d.glob("table_*.md"))
    stems = {m.stem for m in mds}
    csvs = [c for c in sorted(d.glob("table_*.csv")) if c.stem not in stems]
    if not mds and not csvs:
        return na(f"not generated yet: no table_*.md or table_*.csv in {show_path(d, opts.base)} {hint}")
    out = []
    for m in mds:
        out.append(f'<div class="papertable"><p class="src">{esc(m.name)}</p>'
                   f"{markdown_to_html(m.read_text(encoding='utf-8'))}</div>")
    for c in csvs:
        rows = list(csv.reader(io.StringIO(c.read_text(encoding="utf-8"))))
        body = html_table(rows[0], rows[1:]) if rows else na(f"{c.name} is empty")
        out.append(f'<div class="papertable"><p class="src">{esc(c.name)}</p>{body}</div>')
    return "\n".join(out)
