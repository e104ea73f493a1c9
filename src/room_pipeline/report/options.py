"""What goes into the report: the section list, the colour and modality constants, :class:`ReportOptions`."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from ..catalog import RGB_NOISY
from ..errors import ConfigError

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
MARKERS = ("metrics", "anatomy", "input", "ground_truth")


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
