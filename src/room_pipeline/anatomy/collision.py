"""The scope's collision surface: the lumen mesh, decimated under a measured error bound.

Bullet tests every wall triangle whose bounding box overlaps a scope capsule's.
In a lumen barely wider than the scope those boxes reach the wall on all
sides, so the contact cost grows with triangle density, not with the area
actually touched (``benchmarks/simulation.py``: about two thirds of the step
time on the phantom's 1.2 mm-edge mesh).  The render mesh stays fine for the
images; the physics gets a coarser copy (``anatomy/collision_model.obj``, made
once per patient by the mesh stage) whose two-sided distance to the render mesh
is measured, and the reduction is backed off until it is within
``max_error_mm``.  Lengths in metres, bounds in millimetres.
"""
from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh
from .mesh import surface_distance

MM = 1e-3


def _quadric(mesh: Mesh, n_faces: int) -> Mesh:
    """Open3D quadric edge collapse to ``n_faces`` (worked in mm about the centroid, then back to m)."""
    import open3d as o3d

    origin = mesh.vertices.mean(axis=0)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector((mesh.vertices - origin) / MM),
                                  o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    d = m.simplify_quadric_decimation(int(n_faces), boundary_weight=1e3)  # keep open rims in place
    d.remove_degenerate_triangles()
    d.remove_unreferenced_vertices()
    return Mesh(np.asarray(d.vertices) * MM + origin, np.asarray(d.triangles).astype(np.int64))


def collision_surface(mesh: Mesh, fraction: float, max_error_mm: float, max_attempts: int = 4,
                      n_samples: int = 200_000) -> tuple[Mesh, dict]:
    """Decimate ``mesh`` to about ``fraction`` of its faces with max two-sided distance <= ``max_error_mm``.

    Each attempt that misses the bound halves the reduction (fraction -> (1 + fraction) / 2);
    after ``max_attempts`` misses the input is returned unchanged.  Returns the mesh and a
    report (faces in/out, fraction, measured max / p95 distance in mm, attempts).
    Deterministic: the same mesh and arguments give the same bytes.
    """
    used, inv = np.unique(mesh.faces.ravel(), return_inverse=True)   # unreferenced vertices would count as error
    mesh = Mesh(mesh.vertices[used], inv.reshape(-1, 3).astype(np.int64))
    report = {"faces_input": int(mesh.n_faces), "requested_fraction": float(fraction),
              "max_error_bound_mm": float(max_error_mm)}
    if fraction >= 1.0 or mesh.n_faces < 64:
        report.update(faces=int(mesh.n_faces), fraction=1.0, error_max_mm=0.0, error_p95_mm=0.0, attempts=0)
        return mesh, report
    frac = float(fraction)
    for attempt in range(1, max_attempts + 1):
        dec = _quadric(mesh, max(32, round(mesh.n_faces * frac)))
        if dec.n_faces >= 4:
            d = np.concatenate([surface_distance(dec, mesh, n_samples), surface_distance(mesh, dec, n_samples)]) / MM
            emax, e95 = float(d.max()), float(np.percentile(d, 95))
            if emax <= max_error_mm:
                report.update(faces=int(dec.n_faces), fraction=dec.n_faces / mesh.n_faces, error_max_mm=emax,
                              error_p95_mm=e95, attempts=attempt)
                return dec, report
        frac = 0.5 * (1.0 + frac)
    report.update(faces=int(mesh.n_faces), fraction=1.0, error_max_mm=0.0, error_p95_mm=0.0, attempts=max_attempts,
                  note=f"bound {max_error_mm} mm not met in {max_attempts} attempts; full mesh used")
    return mesh, report
