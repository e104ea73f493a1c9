"""``room report``'s command line."""
from __future__ import annotations

import argparse
import html
import os
import sys
from pathlib import Path
from typing import Sequence

from ..errors import ConfigError, RoomError
from .options import ReportOptions
from .page import write_report


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
