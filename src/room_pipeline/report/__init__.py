"""``room report``: one self-contained HTML page describing a generated ROOM dataset.

See :mod:`room_pipeline.report.html` (what the page holds, how it is built, the command line).
Importing this package is cheap: matplotlib, pyvista and the image readers load on first use.
"""
from __future__ import annotations

from .html import SECTIONS, ReportOptions, build_report, main, write_report

__all__ = ["SECTIONS", "ReportOptions", "build_report", "main", "write_report"]
