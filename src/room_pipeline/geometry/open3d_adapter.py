"""The one place Open3D is imported: ray casting and point-to-mesh distance on a triangle mesh.

Open3D's ``RaycastingScene`` works in float32, so every scene is built in a local frame: the mesh's
vertices minus ``origin`` (by default the centre of its bounding box; callers that need the bytes of an
earlier release pass the origin they used), and query points and ray origins are shifted the same way.
Lengths are whatever the caller's mesh uses (metres in this project); results come back as float64
numpy arrays.  Open3D is imported on first use only (it is heavy, and bpy's process must not load it), and
without its viewer: ``open3d/__init__.py`` imports ``open3d.visualization`` unconditionally, whose
``draw_plotly`` imports dash, plotly and IPython (about 0.7-1.1 of the ~1.35 CPU s of ``import open3d``), none of
which this project uses.  :func:`o3d` therefore registers ``open3d.visualization`` as a module that executes the
real package into itself on its first attribute access (:class:`_DeferredModule`): ray casting and distances run
the same compiled code either way, and the viewer still works when something asks for it.
"""
from __future__ import annotations

import importlib.util
import os
import sys
import types
from typing import Any

import numpy as np

_VIEWER = "open3d.visualization"


class _DeferredModule(types.ModuleType):
    """A package created from its spec but not yet executed: the first attribute it lacks executes it."""

    def __getattr__(self, name: str) -> Any:
        self.__class__ = types.ModuleType       # from here on a plain module (also if the execution fails)
        self.__spec__.loader.exec_module(self)
        return getattr(self, name)


def _defer_viewer() -> None:
    """Put an unexecuted ``open3d.visualization`` in ``sys.modules`` before ``import open3d`` (see the module
    docstring).  Not inside IPython: ``open3d/__init__.py`` enables its web viewer in a Jupyter kernel."""
    if "open3d" in sys.modules or _VIEWER in sys.modules or "IPython" in sys.modules:
        return
    spec = importlib.util.find_spec("open3d")
    if spec is None or not spec.submodule_search_locations:
        return
    pkg = os.path.join(list(spec.submodule_search_locations)[0], "visualization")
    viewer = importlib.util.spec_from_file_location(_VIEWER, os.path.join(pkg, "__init__.py"),
                                                    submodule_search_locations=[pkg])
    if viewer is None or viewer.loader is None:
        return
    module = importlib.util.module_from_spec(viewer)
    module.__class__ = _DeferredModule
    sys.modules[_VIEWER] = module


def o3d() -> Any:
    """The ``open3d`` module (imported on first call, its viewer deferred: the module docstring)."""
    if "open3d" not in sys.modules:
        _defer_viewer()
        try:
            import open3d
        except BaseException:
            if type(sys.modules.get(_VIEWER)) is _DeferredModule:
                del sys.modules[_VIEWER]
            raise
        # `import open3d.visualization` found it in sys.modules, so the package attribute is not set yet
        open3d.__dict__.setdefault("visualization", sys.modules[_VIEWER])
    import open3d

    return open3d


class MeshScene:
    """An Open3D ``RaycastingScene`` holding one triangle mesh.

    Args:
        vertices: (N, 3) positions.
        faces: (M, 3) vertex indices.
        origin: the local frame's origin (3,); None: the centre of the vertices' bounding box.

    Attributes:
        scene: the ``open3d.t.geometry.RaycastingScene`` (for casting rays in the local frame).
        origin: (3,) float64, subtracted from every point before it reaches Open3D.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray | None = None) -> None:
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        if origin is None:
            origin = 0.5 * (v.min(axis=0) + v.max(axis=0)) if len(v) else np.zeros(3)
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self._o3d = o3d()
        self.scene = self._o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(self._o3d.core.Tensor((v - self.origin).astype(np.float32)),
                                 self._o3d.core.Tensor(np.asarray(faces).reshape(-1, 3).astype(np.uint32)))

    @classmethod
    def of(cls, mesh, origin: np.ndarray | None = None) -> "MeshScene":
        """Scene of a :class:`~room_pipeline.io.mesh.Mesh` (anything with ``vertices`` and ``faces``)."""
        return cls(mesh.vertices, mesh.faces, origin)

    def tensor(self, a: np.ndarray, dtype=np.float32):
        """``a`` as an Open3D tensor (no shift)."""
        return self._o3d.core.Tensor(np.ascontiguousarray(a, dtype=dtype))

    def _local(self, points: np.ndarray):
        q = np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.origin
        return self.tensor(q)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) unsigned distance of each point (N, 3) to the surface."""
        if len(np.asarray(points).reshape(-1, 3)) == 0:
            return np.zeros(0)
        return self.scene.compute_distance(self._local(points)).numpy().astype(np.float64)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed distance (negative inside a closed mesh) of each point (N, 3)."""
        if len(np.asarray(points).reshape(-1, 3)) == 0:
            return np.zeros(0)
        return self.scene.compute_signed_distance(self._local(points)).numpy().astype(np.float64)

    def closest_points(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) closest point on the surface to each point (N, 3), in the caller's frame."""
        if len(np.asarray(points).reshape(-1, 3)) == 0:
            return np.zeros((0, 3))
        ans = self.scene.compute_closest_points(self._local(points))
        return ans["points"].numpy().astype(np.float64) + self.origin


def surface_points(mesh, n_samples: int = 200_000, seed: int = 0) -> np.ndarray:
    """``mesh``'s vertices plus about ``n_samples`` points uniformly spread over its faces (seeded)."""
    from ..io.mesh import sample_surface

    area = mesh.area()
    spacing = np.sqrt(area / n_samples) if area > 0 else 1.0
    return np.concatenate([mesh.vertices, sample_surface(mesh, spacing, np.random.default_rng(seed),
                                                         max_points=n_samples)])


def surface_distance(a, b, n_samples: int = 200_000, seed: int = 0) -> np.ndarray:
    """Distances from ``a``'s vertices and uniform samples on ``a``'s faces to surface ``b`` (one-sided)."""
    return MeshScene.of(b, origin=b.vertices.mean(axis=0)).distance(surface_points(a, n_samples, seed))
