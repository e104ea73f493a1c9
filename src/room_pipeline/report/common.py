"""Small HTML helpers shared by the sections: escaping, number formatting, data URIs, tables, JSON reads."""
from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def na(why: str) -> str:
    return f'<p class="na">not available: {esc(why)}</p>'


def fmt(v: Any) -> str:
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
        items = [fmt(x) for x in v[:6]]
        return "[" + ", ".join(items) + (", ..." if len(v) > 6 else "") + "]"
    return str(v)


def show_path(path: Path, base: Path | None) -> str:
    """``path`` relative to ``base`` when inside it (stable across clones), else as given."""
    p = Path(path)
    try:
        return p.resolve().relative_to((base or Path.cwd()).resolve()).as_posix() or "."
    except ValueError:
        return p.as_posix()


def read_json(path: Path) -> tuple[Any, str | None]:
    """(document, None), or (None, why) when the file is absent or not JSON."""
    if not path.is_file():
        return None, f"no {path.name}"
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh), None
    except (OSError, ValueError) as exc:
        return None, f"{path.name} is not readable JSON ({exc.__class__.__name__})"


def data_uri(data: bytes, mime: str) -> str:
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
    return data_uri(buf.tobytes(), "image/png")


def jpeg_uri(rgb: np.ndarray, quality: int = 90) -> str:
    """A (H, W, 3) RGB uint8 array as a JPEG ``data:`` URI."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover
        raise RuntimeError("JPEG encoding failed")
    return data_uri(buf.tobytes(), "image/jpeg")


def img_tag(uri: str, alt: str, width: int, height: int, cls: str = "") -> str:
    c = f' class="{cls}"' if cls else ""
    return f'<img{c} src="{uri}" alt="{esc(alt)}" width="{width}" height="{height}">'


def html_table(header: Sequence[str], rows: Iterable[Sequence[str]], cls: str = "data", raw: bool = False) -> str:
    """An HTML table; cells are escaped unless ``raw``."""
    f = (lambda c: c) if raw else esc
    out = [f'<table class="{cls}"><thead><tr>' + "".join(f"<th>{f(h)}</th>" for h in header) + "</tr></thead><tbody>"]
    out += ["<tr>" + "".join(f"<td>{f(c)}</td>" for c in row) + "</tr>" for row in rows]
    out.append("</tbody></table>")
    return "".join(out)
