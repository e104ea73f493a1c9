"""Signed distance field -> watertight lumen surface (``lung_model``), metres, world RAS+.

Steps: crop to the lumen + pad with positive values (the surface closes where
the volume border cuts an airway) -> marching cubes at level 0 in voxel
indices -> affine to world metres -> orientation outward (positive signed
volume) -> clean-up (duplicate vertices/faces, unreferenced vertices,
zero-area faces; optionally the largest component only) -> volume-preserving
Taubin smoothing -> quadric edge-collapse decimation under an error bound
(measured two-sided distance to the pre-decimation surface; ``anatomy/decimate.py``,
the one routine shared with the collision surface) -> optional tetrahedral mesh
(pytetwild) -> the scope's collision surface (``anatomy/collision.py``).

pymeshlab is imported inside the functions only (its Embree clashes with bpy's).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import ConfigError, InputError
from ..io.mesh import Mesh
from ..io.volume import Volume
from .collision import collision_surface
from .decimate import QuadricOptions, decimate_under_bound
from .topology import _components, mesh_topology  # noqa: F401  (mesh_topology: part of this module's API)

SMOOTHING = ("none", "taubin", "hc_laplacian")


@dataclasses.dataclass
class MeshParams:
    """Parameters of :func:`extract_surface`; field names == keys of ``conf/mesh/default.yaml``.

    Attributes:
        keep_largest_component: drop every connected component but the largest.
        smoothing: 'taubin' (volume preserving, default), 'hc_laplacian' or 'none'.
        smoothing_iterations: Taubin (lambda, mu) step pairs / HC passes.
        taubin_lambda, taubin_mu: Taubin factors (mu < -lambda < 0).
        decimation_fraction: target face count as a fraction of the input (1.0 = no decimation).
        decimation_max_error_mm: bound on the max symmetric distance to the pre-decimation surface, mm.
        decimation_p95_error_mm: bound on its 95th percentile, mm.
        decimation_max_retries: rounds after the first before giving up decimation (anatomy/decimate.py).
        decimation_quality_threshold: quadric decimation triangle-quality threshold (0..1).
        preserve_normal: forbid face flips during decimation.
        preserve_topology: forbid topology changes during decimation.
        optimal_placement: place collapsed vertices optimally (else at an end point).
        planar_quadric: add planar quadrics (better triangles in flat regions).
        tetrahedralize: also build a tetrahedral mesh of the lumen with pytetwild.
        tet_edge_length_fraction: pytetwild ideal edge length as a fraction of the bbox diagonal.
    """

    keep_largest_component: bool = False
    smoothing: str = "taubin"
    smoothing_iterations: int = 10
    taubin_lambda: float = 0.5
    taubin_mu: float = -0.53
    decimation_fraction: float = 0.25
    decimation_max_error_mm: float = 0.2
    decimation_p95_error_mm: float = 0.07
    decimation_max_retries: int = 4
    decimation_quality_threshold: float = 0.3
    preserve_normal: bool = True
    preserve_topology: bool = True
    optimal_placement: bool = True
    planar_quadric: bool = True
    tetrahedralize: bool = False
    tet_edge_length_fraction: float = 0.05
    collision_decimation: float = 0.5
    collision_max_error_mm: float = 0.25

    def __post_init__(self) -> None:
        if self.smoothing not in SMOOTHING:
            raise ConfigError(f"mesh.smoothing must be one of {SMOOTHING}, got {self.smoothing!r}")
        if self.smoothing_iterations < 0:
            raise ConfigError(f"mesh.smoothing_iterations must be >= 0, got {self.smoothing_iterations}")
        if not (0.0 < self.decimation_fraction <= 1.0):
            raise ConfigError(f"mesh.decimation_fraction must be in (0, 1], got {self.decimation_fraction}")
        if self.decimation_max_error_mm <= 0 or self.decimation_p95_error_mm <= 0:
            raise ConfigError("mesh.decimation_max_error_mm and decimation_p95_error_mm must be > 0")
        if self.decimation_max_retries < 0:
            raise ConfigError(f"mesh.decimation_max_retries must be >= 0, got {self.decimation_max_retries}")
        if not (0.0 <= self.decimation_quality_threshold <= 1.0):
            raise ConfigError("mesh.decimation_quality_threshold must be in [0, 1]")
        if not (0.0 < self.collision_decimation <= 1.0):
            raise ConfigError(f"mesh.collision_decimation must be in (0, 1], got {self.collision_decimation}")
        if self.collision_max_error_mm <= 0:
            raise ConfigError(f"mesh.collision_max_error_mm must be > 0, got {self.collision_max_error_mm}")
        if not (0.0 < self.tet_edge_length_fraction < 1.0):
            raise ConfigError("mesh.tet_edge_length_fraction must be in (0, 1)")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "MeshParams":
        """Build from a config mapping; unknown keys raise :class:`ConfigError` naming the key."""
        return params_from_dict(cls, d, "mesh")


@dataclasses.dataclass
class MeshResult:
    """Output of :func:`extract_surface`.

    Attributes:
        mesh: closed lumen surface, world RAS+ metres, outward oriented.
        collision: the scope simulation's copy of ``mesh``, decimated under ``collision_max_error_mm``.
        tets: (vertices (N,3) metres, tetrahedra (M,4) int64) or None.
        report: JSON-serialisable figures (counts, topology, volume m^3, area m^2, errors m).
    """

    mesh: Mesh
    tets: tuple[np.ndarray, np.ndarray] | None
    report: dict
    collision: Mesh | None = None


# --------------------------------------------------------------------------- steps
def _marching_cubes(sdf: Volume) -> Mesh:
    """Zero level of the SDF (metres, negative inside) as a closed mesh in world metres."""
    from skimage.measure import marching_cubes

    d = np.asarray(sdf.data, dtype=np.float32)
    inside = d < 0
    if not inside.any() or inside.all():
        raise InputError("SDF has no zero crossing: the lumen is empty (or fills the whole volume)")
    nz = [np.nonzero(inside.any(axis=ax))[0] for ax in ((1, 2), (0, 2), (0, 1))]
    lo = np.array([max(int(a[0]) - 2, 0) for a in nz])
    hi = np.array([min(int(a[-1]) + 3, s) for a, s in zip(nz, d.shape)])
    sub = d[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    pos = float(np.abs(sdf.spacing).max())
    sub = np.pad(sub, 1, mode="constant", constant_values=pos)  # closes airways cut by the border
    # an exact zero at a grid point makes coincident vertices (pinches): nudge it outward
    tiny = 1e-6 * float(sdf.spacing.min())
    sub = np.where(sub == 0, np.float32(tiny), sub)
    verts, faces, _, _ = marching_cubes(sub, level=0.0, allow_degenerate=False)
    ijk = verts.astype(np.float64) + (lo - 1)
    mesh = Mesh(sdf.index_to_world(ijk), faces.astype(np.int64))
    if mesh.signed_volume() < 0:
        mesh.faces = mesh.faces[:, ::-1].copy()
    return mesh


def _to_ms(mesh: Mesh, scale: float):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.vertices * scale, face_matrix=mesh.faces.astype(np.int32)))
    return ms


def _from_ms(ms, scale: float) -> Mesh:
    cm = ms.current_mesh()
    return Mesh(cm.vertex_matrix() / scale, cm.face_matrix().astype(np.int64))


def _clean(ms) -> None:
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_unreferenced_vertices()


def _largest_component(mesh: Mesh) -> Mesh:
    n, lab = _components(mesh.n_vertices, mesh.faces)
    if n <= 1:
        return mesh
    keep = lab == np.argmax(np.bincount(lab))
    f = mesh.faces[keep]
    used, newf = np.unique(f, return_inverse=True)
    return Mesh(mesh.vertices[used], newf.reshape(-1, 3))


def _decimate(mesh: Mesh, params: MeshParams, report: dict) -> Mesh:
    """Quadric edge collapse to ``decimation_fraction`` of the faces under the error bounds (anatomy/decimate.py)."""
    opts = QuadricOptions(quality_threshold=params.decimation_quality_threshold, preserve_normal=params.preserve_normal,
                          preserve_topology=params.preserve_topology, optimal_placement=params.optimal_placement,
                          planar_quadric=params.planar_quadric)
    dec, r = decimate_under_bound(mesh, params.decimation_fraction, params.decimation_max_error_mm,
                                  params.decimation_p95_error_mm, options=opts,
                                  max_rounds=params.decimation_max_retries + 1)
    report.update(decimation_requested_fraction=float(params.decimation_fraction),
                  decimation_fraction=r["fraction"], decimation_error_max_m=r["error_max_mm"] * MM,
                  decimation_error_p95_m=r["error_p95_mm"] * MM, decimation_attempts=r["rounds"],
                  decimation_protected_faces=r["protected_faces"])
    if "note" in r:
        report["decimation_note"] = r["note"]
    return dec


def tetrahedralize(mesh: Mesh, edge_length_fraction: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh of the closed surface with pytetwild: (vertices (N,3) m, tets (M,4) int64)."""
    import os
    import tempfile

    import pytetwild

    scale = 1.0 / MM
    # fTetWild writes '__tracked_surface.stl' into the working directory: run it in a scratch one
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="room_tetwild_") as tmp:
        os.chdir(tmp)
        try:
            v, t = pytetwild.tetrahedralize(mesh.vertices * scale, mesh.faces.astype(np.int32),
                                            edge_length_fac=float(edge_length_fraction), quiet=True)
        finally:
            os.chdir(cwd)
    return np.asarray(v, dtype=np.float64) / scale, np.asarray(t, dtype=np.int64)


# --------------------------------------------------------------------------- API
def extract_surface(sdf: Volume, params: MeshParams) -> MeshResult:
    """Closed lumen surface of an SDF (metres, negative inside) in world RAS+ metres.

    Raises:
        InputError: the SDF has no zero crossing (empty lumen).
    """
    report: dict = {}
    mesh = _marching_cubes(sdf)
    report["n_faces_marching_cubes"] = mesh.n_faces
    scale = 1.0 / MM
    ms = _to_ms(mesh, scale)
    _clean(ms)
    mesh = _from_ms(ms, scale)
    if params.keep_largest_component:
        mesh = _largest_component(mesh)
    if params.smoothing != "none" and params.smoothing_iterations > 0:
        ms = _to_ms(mesh, scale)
        if params.smoothing == "taubin":
            ms.apply_coord_taubin_smoothing(lambda_=params.taubin_lambda, mu=params.taubin_mu,
                                            stepsmoothnum=params.smoothing_iterations)
        else:
            for _ in range(params.smoothing_iterations):
                ms.apply_coord_hc_laplacian_smoothing()
        mesh = _from_ms(ms, scale)
    report["n_faces_before_decimation"] = mesh.n_faces
    mesh = _decimate(mesh, params, report)
    if mesh.signed_volume() < 0:
        mesh.faces = mesh.faces[:, ::-1].copy()
    topo = mesh_topology(mesh)
    report.update(n_faces=mesh.n_faces, n_vertices=mesh.n_vertices, watertight=topo["watertight"],
                  manifold=topo["manifold"], orientation_consistent=topo["orientation_consistent"],
                  boundary_edges=topo["boundary_edges"], non_manifold_edges=topo["non_manifold_edges"],
                  non_manifold_vertices=topo["non_manifold_vertices"],
                  euler_characteristic=topo["euler_characteristic"], n_components=topo["components"],
                  volume_m3=mesh.signed_volume(), area_m2=mesh.area())
    tets = None
    if params.tetrahedralize:
        tets = tetrahedralize(mesh, params.tet_edge_length_fraction)
        report.update(n_tets=int(len(tets[1])), n_tet_vertices=int(len(tets[0])))
    collision, report["collision"] = collision_surface(mesh, params.collision_decimation,
                                                       params.collision_max_error_mm)
    return MeshResult(mesh=mesh, tets=tets, report=report, collision=collision)
