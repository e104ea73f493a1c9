"""Distances to the TRUE lumen surface (the rendered mesh), through Open3D's RaycastingScene.

``TrueLumen(mesh).signed_distance(points)``: metres, negative inside the closed lumen surface (the air;
the mesh is watertight, normals from air into tissue), positive in the tissue.  A scope sphere of radius
r at a point collides with the wall when ``signed_distance > -r``.  Used to score what a plan made from a
depth map would do in the real anatomy (the paper could not measure this) and the closed-loop episodes'
distance kept from the wall.
"""
from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh


class TrueLumen:
    """Signed distance to a closed lumen mesh (world RAS+ metres)."""

    def __init__(self, mesh: Mesh) -> None:
        from ..geometry.open3d_adapter import MeshScene

        self._scene = MeshScene.of(mesh)              # local frame about the bounding box's centre
        self.origin = self._scene.origin

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distance of world points (N, 3) to the surface, m; negative inside the lumen."""
        return self._scene.signed_distance(points)

    def path_report(self, points_world: np.ndarray, radius: float) -> dict:
        """Clearance of scope spheres (radius m) along a path: min wall distance, collision flag, first hit index."""
        sd = self.signed_distance(points_world)
        clearance = -sd - radius                       # > 0: the sphere is clear of the wall
        hit = np.flatnonzero(clearance < 0)
        return {"min_wall_distance_mm": float((-sd).min() * 1e3) if len(sd) else None,
                "min_sphere_clearance_mm": float(clearance.min() * 1e3) if len(sd) else None,
                "collides_with_true_lumen": bool(len(hit)),
                "first_collision_index": int(hit[0]) if len(hit) else None,
                "outside_lumen_points": int((sd > 0).sum())}
