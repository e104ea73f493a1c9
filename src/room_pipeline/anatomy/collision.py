"""The scope's collision surface: the lumen mesh, decimated under a measured error bound.

Bullet tests every wall triangle whose bounding box overlaps a scope capsule's.
In a lumen barely wider than the scope those boxes reach the wall on all
sides, so the contact cost grows with triangle density, not with the area
actually touched (``benchmarks/simulation.py``: about two thirds of the step
time on the phantom's 1.2 mm-edge mesh; ``benchmarks/collision_speed.py``:
the simulate CPU time against the collision surface's faces and error bound on
ATM_001).  The render mesh stays fine for the images; the physics gets a coarser
copy (``anatomy/collision_model.obj``, made once per patient by the mesh stage)
whose two-sided distance to the render mesh is measured and held within
``max_error_mm`` (``anatomy/decimate.py``: the places that miss keep their
faces, the rest is reduced).  Lengths in metres, bounds in millimetres.
"""
from __future__ import annotations

from ..io.mesh import Mesh
from .decimate import decimate_under_bound


def collision_surface(mesh: Mesh, fraction: float, max_error_mm: float, max_rounds: int = 8,
                      n_samples: int = 200_000) -> tuple[Mesh, dict]:
    """Decimate ``mesh`` to about ``fraction`` of its faces with max two-sided distance <= ``max_error_mm``.

    See :func:`~room_pipeline.anatomy.decimate.decimate_under_bound` (its report is returned: faces in/out,
    fraction, the measured max / p95 distance both ways in mm, protected faces, rounds); after
    ``max_rounds`` misses the input is returned unchanged.  Deterministic.
    """
    return decimate_under_bound(mesh, fraction, max_error_mm, max_rounds=max_rounds, n_samples=n_samples)
