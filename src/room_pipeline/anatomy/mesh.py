"""Signed distance field -> watertight lumen surface (``lung_model``), metres, world RAS+.

Steps: crop to the lumen + pad with positive values (the surface closes where
the volume border cuts an airway) -> marching cubes at level 0 in voxel
indices -> affine to world metres -> orientation outward (positive signed
volume) -> clean-up (duplicate vertices/faces, unreferenced vertices,
zero-area faces; optionally the largest component only) -> volume-preserving
Taubin smoothing -> quadric edge-collapse decimation under an error bound
(measured symmetric distance to the pre-decimation surface; the reduction is
backed off until the bound holds) -> optional tetrahedral mesh (pytetwild).

pymeshlab is imported inside the functions only (its Embree clashes with bpy's).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import ConfigError, InputError
from ..io.mesh import Mesh
from ..io.volume import Volume

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
        decimation_max_retries: how often the reduction is halved before giving up decimation.
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


# --------------------------------------------------------------------------- topology
def _components(n_vertices: int, faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of faces (sharing a vertex): (count, label per face)."""
    if len(faces) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    rows = np.repeat(faces[:, 0], 2)
    cols = faces[:, 1:].reshape(-1)
    g = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    flab = lab[faces[:, 0]]
    uniq, flab = np.unique(flab, return_inverse=True)
    return len(uniq), flab


def mesh_topology(mesh: Mesh) -> dict:
    """Topology figures of a triangle mesh, computed in numpy.

    Returns boundary_edges, non_manifold_edges (shared by > 2 faces),
    non_manifold_vertices (faces around the vertex form more than one fan),
    watertight (no boundary or non-manifold edge), manifold (no non-manifold
    edge or vertex), orientation_consistent (every edge used once in each
    direction where it has two faces), components, euler_characteristic (V - E + F
    over referenced vertices), n_vertices, n_faces.
    """
    f = mesh.faces
    nv = mesh.n_vertices
    if len(f) == 0:
        return {"n_vertices": nv, "n_faces": 0, "boundary_edges": 0, "non_manifold_edges": 0,
                "non_manifold_vertices": 0, "watertight": False, "manifold": True,
                "orientation_consistent": True, "components": 0, "euler_characteristic": 0}
    he = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)  # directed half-edges
    und = np.sort(he, axis=1)
    key = und[:, 0] * np.int64(nv) + und[:, 1]
    ukey, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    boundary = int(np.sum(cnt == 1))
    nonman_e = int(np.sum(cnt > 2))
    dkey = he[:, 0] * np.int64(nv) + he[:, 1]
    _, dcnt = np.unique(dkey, return_counts=True)
    # consistent: no directed half-edge repeated (two faces traversing an edge the same way)
    consistent = bool(np.all(dcnt == 1))
    # non-manifold vertices: link of the vertex has more than one connected piece
    corners = np.concatenate([f[:, [0, 1, 2]], f[:, [1, 2, 0]], f[:, [2, 0, 1]]])  # (centre, a, b)
    c, a, b = corners[:, 0], corners[:, 1], corners[:, 2]
    ka = c * np.int64(nv) + a
    kb = c * np.int64(nv) + b
    nodes, node_inv = np.unique(np.concatenate([ka, kb]), return_inverse=True)
    m = len(corners)
    g = sparse.coo_matrix((np.ones(m, dtype=np.int8), (node_inv[:m], node_inv[m:])), shape=(len(nodes), len(nodes)))
    _, lab = connected_components(g, directed=False)
    centre = nodes // nv
    pairs = np.unique(np.stack([centre, lab], axis=1), axis=0)
    pieces = np.bincount(pairs[:, 0], minlength=nv)
    nonman_v = int(np.sum(pieces > 1))
    used = np.unique(f)
    ncomp, _ = _components(nv, f)
    return {"n_vertices": int(nv), "n_faces": int(len(f)), "boundary_edges": boundary,
            "non_manifold_edges": nonman_e, "non_manifold_vertices": nonman_v,
            "watertight": bool(boundary == 0 and nonman_e == 0),
            "manifold": bool(nonman_e == 0 and nonman_v == 0),
            "orientation_consistent": consistent, "components": int(ncomp),
            "euler_characteristic": int(len(used) - len(ukey) + len(f))}


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


def surface_distance(a: Mesh, b: Mesh, n_samples: int = 200_000, seed: int = 0) -> np.ndarray:
    """Distances (metres) from a's vertices and uniform samples on a's faces to surface b."""
    import open3d as o3d

    from ..io.mesh import sample_surface

    origin = b.vertices.mean(axis=0)
    area = a.area()
    spacing = np.sqrt(area / n_samples) if area > 0 else 1.0
    pts = np.concatenate([a.vertices, sample_surface(a, spacing, np.random.default_rng(seed), max_points=n_samples)])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((b.vertices - origin).astype(np.float32)),
                        o3d.core.Tensor(b.faces.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor((pts - origin).astype(np.float32))).numpy().astype(np.float64)


def _decimate(mesh: Mesh, params: MeshParams, report: dict) -> Mesh:
    """Quadric edge collapse to ``decimation_fraction`` of the faces, backed off until the error bound holds."""
    frac = float(params.decimation_fraction)
    report["decimation_requested_fraction"] = frac
    if frac >= 1.0:
        report.update(decimation_fraction=1.0, decimation_error_max_m=0.0, decimation_error_p95_m=0.0,
                      decimation_attempts=0)
        return mesh
    scale = 1.0 / MM  # work in mm: pymeshlab's thresholds behave better at unit scale
    max_err, p95_err = params.decimation_max_error_mm * MM, params.decimation_p95_error_mm * MM
    for attempt in range(params.decimation_max_retries + 1):
        ms = _to_ms(mesh, scale)
        target = max(8, int(round(mesh.n_faces * frac)))
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=target, qualitythr=params.decimation_quality_threshold,
            preserveboundary=True, preservenormal=params.preserve_normal,
            preservetopology=params.preserve_topology, optimalplacement=params.optimal_placement,
            planarquadric=params.planar_quadric, autoclean=True)
        _clean(ms)
        dec = _from_ms(ms, scale)
        d = np.concatenate([surface_distance(dec, mesh), surface_distance(mesh, dec)])
        emax, e95 = float(d.max()), float(np.percentile(d, 95))
        topo = mesh_topology(dec)
        ok = emax <= max_err and e95 <= p95_err and topo["watertight"] and topo["manifold"]
        if ok:
            report.update(decimation_fraction=dec.n_faces / mesh.n_faces, decimation_error_max_m=emax,
                          decimation_error_p95_m=e95, decimation_attempts=attempt + 1)
            return dec
        frac = min(1.0, 0.5 * (1.0 + frac))  # halve the reduction
        if frac >= 0.99:
            break
    report.update(decimation_fraction=1.0, decimation_error_max_m=0.0, decimation_error_p95_m=0.0,
                  decimation_attempts=params.decimation_max_retries + 1,
                  decimation_note="error bound not met at any tried reduction; mesh left undecimated")
    return mesh


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
    from .collision import collision_surface

    collision, report["collision"] = collision_surface(mesh, params.collision_decimation,
                                                       params.collision_max_error_mm)
    return MeshResult(mesh=mesh, tets=tets, report=report, collision=collision)
