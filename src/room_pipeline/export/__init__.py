"""Exports of a rendered sequence to the formats of neighbouring tools, with the ground-truth poses.

``export_sequence(seq_dir, out_dir, fmt)`` with ``fmt`` one of

``colmap``      COLMAP text model ``sparse/0/{cameras,images,points3D}.txt`` + ``images/``
                (:mod:`room_pipeline.export.colmap`; pycolmap reads it)
``nerfstudio``  ``transforms.json`` (nerfstudio / instant-ngp, OpenGL camera) + ``images/``,
                ``depth/``, ``sparse_points.ply`` (:mod:`room_pipeline.export.nerfstudio`)
``tum``         ``groundtruth.txt``, a TUM RGB-D trajectory (:mod:`room_pipeline.export.tum`)
``ply``         ``points/frame_NNNN.ply``, every frame's point cloud (camera or world frame), built on
                demand from depth when the render stage wrote none (:mod:`room_pipeline.export.ply`)

Every export also writes ``room_export.json`` (format, options, source, conventions).  The
export is built in a temporary folder next to ``out_dir`` and renamed onto it when complete, so
``out_dir`` never holds a partial export; an existing non-empty ``out_dir`` is replaced only with
``overwrite=True``.  Same sequence + options -> the same bytes.

Command line (``main``)::

    room export --format {colmap,nerfstudio,tum,ply} SEQ OUT [--overwrite] [--images rgb|rgb_noisy|none]
                [--depth png16|npy|none] [--point-stride N] [--frame camera|world]
"""
from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator

from .. import __version__
from ..catalog import RGB_SOURCES
from ..conventions import metadata_block
from ..errors import ConfigError, InputError, RoomError
from ..io.atomic import write_json

FORMATS = ("colmap", "nerfstudio", "tum", "ply")
#: options each format takes (keyword -> default)
OPTIONS: dict[str, dict[str, Any]] = {
    "colmap": {"images": "rgb", "point_stride": 16},
    "nerfstudio": {"images": "rgb", "depth": "png16", "point_stride": 16},
    "tum": {},
    "ply": {"point_stride": 1, "frame": "camera"},
}


@contextlib.contextmanager
def atomic_dir(out_dir: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder next to ``out_dir``; on success it becomes ``out_dir``.

    A non-empty existing ``out_dir`` raises InputError unless ``overwrite``; then it is moved
    aside, replaced and deleted.  On failure the temporary folder is removed and ``out_dir`` is
    left as it was.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"export target exists and is not a folder: {out}")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(f"export target {out} exists and is not empty (use overwrite / --overwrite)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o755)
        if out.is_dir() and any(out.iterdir()):
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
            os.replace(out, old / "x")
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)          # also onto an empty folder
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _inside(a: Path, b: Path) -> bool:
    """True when ``a`` is ``b`` or lies inside it."""
    a, b = a.resolve(), b.resolve()
    return a == b or b in a.parents


def export_sequence(seq_dir: str | os.PathLike, out_dir: str | os.PathLike, fmt: str, *,
                    overwrite: bool = False, **options: Any) -> dict[str, Any]:
    """Export the rendered sequence ``seq_dir`` as ``fmt`` into the folder ``out_dir`` (atomically).

    ``options`` (per format, defaults in :data:`OPTIONS`): ``images`` -- frames copied to
    ``images/``: 'rgb' or 'rgb_noisy' (COLMAP also takes None: no copies); ``point_stride`` --
    pixels between the depth samples of the sparse points, 0 = none (COLMAP, nerfstudio);
    ``depth`` -- 'png16', 'npy' or None (nerfstudio).  Returns a summary dict (also written as
    ``room_export.json``).  Bad input: InputError / ConfigError, one line.
    """
    from ..dataset.reader import SequenceReader

    if fmt not in FORMATS:
        raise ConfigError(f"export format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    unknown = sorted(set(options) - set(OPTIONS[fmt]))
    if unknown:
        raise ConfigError(f"export {fmt}: unknown options {unknown} (known: {sorted(OPTIONS[fmt]) or 'none'})")
    opts = {**OPTIONS[fmt], **options}
    seq, out = Path(seq_dir), Path(out_dir)
    reader = SequenceReader(seq, modalities=())
    if _inside(out, seq) or _inside(seq, out):
        raise InputError(f"export folder {out} and sequence {seq} must not contain each other")
    with atomic_dir(out, overwrite) as tmp:
        if fmt == "colmap":
            from .colmap import write_colmap
            summary = write_colmap(reader, tmp, **opts)
        elif fmt == "nerfstudio":
            from .nerfstudio import write_nerfstudio
            summary = write_nerfstudio(reader, tmp, **opts)
        elif fmt == "ply":
            from .ply import write_points
            summary = write_points(reader, tmp, **opts)
        else:
            from .tum import write_tum
            summary = write_tum(reader, tmp)
        summary = {"format": fmt, "options": opts, "source": f"{seq.resolve().parent.name}/{seq.resolve().name}",
                   "frames": len(reader), "room_pipeline_version": __version__, **summary,
                   "conventions": metadata_block()}
        write_json(tmp / "room_export.json", summary)
    return summary


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``room export`` arguments, on ``parser`` (a sub-command's) or a new one."""
    p = parser or argparse.ArgumentParser(prog="room export", description="export a rendered sequence")
    p.add_argument("--format", "-f", required=True, choices=FORMATS, dest="format")
    p.add_argument("seq", help="rendered sequence folder (<output_dir>/<patient>/<sequence>)")
    p.add_argument("out", help="export folder (created; replaced only with --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty export folder")
    p.add_argument("--images", choices=(*RGB_SOURCES, "none"), default=None,
                   help="frames to copy (colmap, nerfstudio; default rgb; colmap also takes none)")
    p.add_argument("--depth", choices=("png16", "npy", "none"), default=None,
                   help="nerfstudio depth files: png16 (1e-5 m units, default), npy (float32 m), none")
    p.add_argument("--point-stride", type=int, default=None, dest="point_stride",
                   help="pixels between depth samples of the sparse points (colmap, nerfstudio; 0 = none; default 16; "
                        "ply: default 1)")
    p.add_argument("--frame", choices=("camera", "world"), default=None,
                   help="ply: coordinate frame of the points (default camera)")
    return p


def run_args(args: argparse.Namespace) -> int:
    """Run a parsed ``room export`` command line; prints one summary line."""
    opts: dict[str, Any] = {}
    for key in ("images", "depth", "point_stride", "frame"):
        val = getattr(args, key, None)
        if val is None:
            continue
        if key not in OPTIONS[args.format]:
            raise ConfigError(f"--{key.replace('_', '-')} does not apply to the {args.format} export")
        opts[key] = None if val == "none" else val
    s = export_sequence(args.seq, args.out, args.format, overwrite=args.overwrite, **opts)
    print(f"room export: {args.format} of {s['source']} ({s['frames']} frames) -> {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``room export ...``: parse ``argv``, export; bad input -> one line ``room: error: ...``, exit 2."""
    args = build_parser().parse_args(argv)
    try:
        return run_args(args)
    except RoomError as exc:
        print(f"room: error: {exc}", file=sys.stderr)
        return 2
