"""``room report``: a self-contained HTML report of a generated dataset (one file, no network).

Modules, one job each: :mod:`.options` (what goes in), :mod:`.discovery` (patients and sequences),
:mod:`.common` (HTML helpers), :mod:`.colour` (colour maps), :mod:`.sections` (summary, thumbnails,
real vs synthetic), :mod:`.scene` and :mod:`.draw3d` (the 3-D view),
:mod:`.navigation` (the navigation demonstration), :mod:`.metrics`, :mod:`.plots`
(benchmark plots), :mod:`.tables` (paper tables; Markdown by markdown-it-py), :mod:`.page` (the page)
and :mod:`.cli` (``room report``).  Importing this package is cheap: matplotlib, pyvista and the image
readers load on first use.

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
    ``navigation``  only when the dataset holds ``room navigate demo`` output (:mod:`.navigation`): per
                    planned frame, the RGB with the projected path and a 3-D view of the point cloud,
                    the path, the scope's collision spheres and the true lumen mesh near them.
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

from .cli import main
from .options import SECTIONS, ReportOptions
from .page import build_report, write_report

__all__ = ["SECTIONS", "ReportOptions", "build_report", "main", "write_report"]
