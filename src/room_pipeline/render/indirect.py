"""Multi-bounce diffuse inter-reflection for the ray caster: precomputed light transport on the mesh.

A lumen is nearly closed, so most of the light a wall receives comes from other walls, after one or
more diffuse bounces (Cycles needs >= 8 bounces to converge inside an airway:
benchmarks/results/cycles_reference.md).  The geometry is static per patient, so the transport between
surface points is computed once, and only the direct light changes per frame.

Points
    The vertices of the render mesh, with their area-weighted normals turned into the lumen (the mesh's
    normals point from air into tissue, ``conventions.MESH_ORIENTATION``).

Gather matrix (once per mesh)
    From each point ``i``, ``K`` (``rays_per_point``) cosine-weighted directions about its normal
    (stratified: a ``sqrt(K) x sqrt(K)`` jittered grid when ``K`` is a square, seeded from ``seed`` and
    the point index, so the matrix is the same bytes on every run) are cast with Open3D from ``eps``
    off the surface.  A ray that hits triangle ``(a, b, c)`` at barycentrics ``(1-u-v, u, v)`` adds
    ``(1-u-v)/K, u/K, v/K`` to row ``i``, columns ``a, b, c`` of the sparse ``G`` (duplicates summed);
    a ray that escapes (an open end) or hits a back face adds nothing.  Then for a Lambertian surface
    the irradiance a point gathers from the others is ``E_i^ind = sum_j G_ij rho_j E_j``: with
    cosine-weighted sampling ``E = pi mean_k L_k`` and the outgoing radiance of a diffuse wall is
    ``L_j = rho_j E_j / pi`` (Lambert's 1/pi cancels the pi).  In a closed surface every row of ``G``
    sums to 1 (tested: the white furnace).

Per frame
    1. Direct irradiance at every point from the tip light, exactly as the per-pixel direct term of
       :mod:`~room_pipeline.render.shading`: ``E = P/(4 pi) max(n.l, 0) / r^2`` times the LED's
       ``cos^mu`` profile about the optical axis and the falloff option (:func:`shading.light_profile`),
       with a shadow ray from the point to the light (``shadows``; the light sits next to the lens, so
       every wall the camera sees is lit, but walls round a bend are not).
    2. ``bounces`` Jacobi steps of ``E <- E_dir + G (rho E)`` per colour channel: ``E_1 = G (rho_dir
       E_dir)``, ``E_{n+1} = G (rho_dir E_dir + rho E_n)``, where ``rho_dir`` / ``rho`` are what a wall passes
       on of the tip light / of the bounced light.  **Default (``caustics`` off): both are the albedo**, a
       pure Lambertian wall.  That is the light Cycles computes as this project runs it: render/blender.py
       turns ``caustics_reflective`` off, and Cycles then drops the Principled BSDF's specular layer (and
       with it the layer's ``1 - A`` weight on the diffuse base: inferred from the measurements, not read in
       Blender's source) at every surface a diffuse bounce reaches,
       so only the first surface of a camera path (or one reached by glossy bounces only) is wet.  Measured
       with ``glossy_bounces = 0`` in Cycles: its glossy bounces carry 2 % of the light of a trachea view, the
       wet transport below 15 % (benchmarks/results/realism_psnr_split_trachea_glossy_off_s10.md); the wet
       transport made the far walls of the trachea 19 % too bright.  With ``caustics`` the walls keep the
       layer: ``rho = albedo (1 - Abar) + Abar`` with ``Abar = 2 int A(mu) mu dmu`` the wet layer's mean
       directional albedo (:func:`shading.specular_albedo`; the Principled BSDF scales the diffuse base by
       ``1 - A``); ``rho_dir`` is the same for the tip light's single direction, ``albedo (1 - A(n.l)) +
       A(n.l)`` (its specular share re-emitted as if diffuse).  The mirror ray of a pixel (``glossy``) sees
       a wall reached by a glossy bounce, which is wet either way: ``(rho_dir E_dir + rho E_ind) / pi`` with
       the layered values (:meth:`Radiosity.frame`).  After ``n`` steps ``E`` holds paths of up to ``n``
       bounces, as Cycles' ``max_bounces = n`` does; the indirect part is ``E - E_dir``.
    3. At each pixel, the indirect irradiance interpolated with the hit's barycentrics, times
       ``(1 - F0) albedo(x) / pi`` (the pixel's own albedo: the per-pixel appearance) is added to the
       direct radiance.

Transport mesh (``IndirectConfig.max_edge_mm``)
    With point samples at the vertices, the piecewise-linear field of the vertex values is not the field:
    the tip light's irradiance ``I cos / r^2`` peaks inside the large flat triangles of the decimated
    trachea beside the scope (edges ~3 mm at 7-10 mm from the light), and the linear interpolant of its
    vertex samples under-counts the power those walls pass on (patient_000's bifurcation view: 13 % under
    on the walls 6-10 mm from the light; every later bounce loses ~1.5 % more against a brute-force path
    tracer of the same diffuse transport, benchmarks/realism_indirect_pt.py).
    With ``max_edge_mm`` > 0 the points are the vertices of the render mesh refined by midpoint splits
    until no edge is longer (:mod:`~room_pipeline.render.refine`: the same flat triangles, sampled finer;
    albedo and normals interpolated linearly at the new vertices, as the pixels shade them), so the tip
    light's irradiance peak inside the coarse triangles beside the scope is sampled and passed on.  The
    render mesh's vertices keep their indices (the first ``n_render`` points), so the pixels interpolate
    the transport's values at them on the render mesh's triangles unchanged: the indirect field is
    smooth; the bias was in what the walls pass on.  Every array of this class is over the transport
    points; the mirror rays hit the refined mesh.  2 mm: 39.64 dB (patient_000 bifurcation, was 37.50)
    and 41.21 dB (patient_001 trachea, was 39.48) against the 1024-spp Cycles references
    (benchmarks/results/cycles_residual_s12*_edge2.md); the default (render.indirect_max_edge_mm 2.0)
    since session 12, judges on every default frame in benchmarks/results/realism_refit_run_s12_edge2.md.
    Hat-weighted patch means of the vertex values (session 12's ``render.indirect_patch``) fixed the same
    bias less well (39.87 / 38.40 dB, benchmarks/results/cycles_residual_s12*_patch_direct.md): removed.

What it leaves out: the glossy lobe's direction (its share is re-emitted as if diffuse where it is kept),
the irradiance's variation inside a triangle beyond linear interpolation, and the texture's
detail finer than the vertices in the light it re-emits.  Units: irradiance W/m^2, radiance W/(m^2 sr),
lengths metres.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .scene import TipLight, TissueMaterial
from .shading import light_profile, specular_albedo


@dataclasses.dataclass(frozen=True)
class IndirectConfig:
    """Knobs of the precomputed inter-reflection (module docstring).

    bounces: diffuse bounces after the first hit (0 = off; Cycles' ``max_bounces``);
    rays_per_point: gather rays per mesh vertex (K); seed: their sampling seed;
    shadows: shadow rays for the direct light at the points; eps_m: ray start offset off the surface;
    glossy: the wet layer's specular reflection of the bounced light (module docstring), seen at the pixels
    by one mirror ray every ``glossy_stride`` pixels;
    caustics: whether walls reached by bounced light keep their wet layer (its specular share ``A``, white,
    and the ``1 - A`` layering of the diffuse base) in the light they pass on (step 2 of the module
    docstring); False (the default): they pass on ``albedo`` E, pure Lambertian, as Cycles renders with
    ``caustics_reflective`` off (render/blender.py sets it off for every Cycles render, the references too);
    max_edge_mm: > 0 runs the transport on the render mesh refined until no edge is longer (mm; module
    docstring, "Transport mesh"); 0 (default): on the render mesh itself.
    """

    bounces: int = 0
    rays_per_point: int = 64
    seed: int = 0
    shadows: bool = True
    eps_m: float = 1e-5
    glossy: bool = True
    glossy_stride: int = 2
    caustics: bool = False
    max_edge_mm: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_edge_mm) and self.max_edge_mm >= 0):
            raise ValueError(f"indirect: max_edge_mm must be >= 0 (0 = the render mesh), got {self.max_edge_mm}")
        if self.bounces < 0 or self.rays_per_point < 1 or not self.eps_m > 0 or self.glossy_stride < 1:
            raise ValueError(f"indirect: bounces >= 0, rays_per_point >= 1 and eps_m > 0 required, got "
                             f"{self.bounces}, {self.rays_per_point}, {self.eps_m}")


def vertex_normals_into_lumen(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals pointing into the lumen (minus the mesh's air->tissue normals)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    return -vn / np.where(ln > 0, ln, 1.0)


def _frames(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) completing each unit normal to an orthonormal frame (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    s = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return t, s


def cosine_directions(normals: np.ndarray, k: int, seed: int) -> np.ndarray:
    """(N, K, 3) cosine-weighted unit directions about each normal; stratified when K is a square; seeded."""
    n = np.asarray(normals, dtype=np.float64)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), len(n), int(k)]))
    m = int(round(math.sqrt(k)))
    if m * m == k:                      # jittered m x m grid on the unit square
        gi, gj = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
        u1 = (gi.reshape(-1) + rng.random((len(n), k))) / m
        u2 = (gj.reshape(-1) + rng.random((len(n), k))) / m
    else:
        u1, u2 = rng.random((len(n), k)), rng.random((len(n), k))
    r = np.sqrt(u1)
    phi = 2 * math.pi * u2
    x, y, z = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0.0))
    t, s = _frames(n)
    return x[..., None] * t[:, None] + y[..., None] * s[:, None] + z[..., None] * n[:, None]


#: gather matrices built in this process, keyed by the mesh's bytes and the sampling knobs (at most
#: ``_G_CACHE_SIZE``; a render stage builds its meter, its probe and its in-process worker on one mesh)
_G_CACHE: dict[tuple, object] = {}
_G_CACHE_SIZE = 2


def _columns_product(g, x: np.ndarray) -> np.ndarray:
    """``g @ x`` (float32, (V, 3)) one column at a time: SciPy's single-vector CSR product sums each row in
    the same order as its multi-vector one (the same bytes, tests/test_indirect.py) and was faster on this
    project's gather matrices (the render stage's time: README, Quick start)."""
    xf = np.asfortranarray(x, dtype=np.float32)
    out = np.empty((g.shape[0], xf.shape[1]), dtype=np.float32)
    for c in range(xf.shape[1]):
        out[:, c] = g @ xf[:, c]
    return out


def gather_cache() -> dict:
    """This process's gather matrices (key -> CSR), to hand to worker processes (:func:`adopt_gather_cache`)."""
    return dict(_G_CACHE)


def adopt_gather_cache(entries: dict | None) -> None:
    """Install gather matrices built by another process on the same meshes and knobs (the render stage's
    driver builds one for its exposure meter; its workers reuse it instead of casting the same rays again)."""
    for key, g in (entries or {}).items():
        if key not in _G_CACHE:
            _remember_gather(key, g)


def _remember_gather(key: tuple, g) -> None:
    """Keep ``g`` under ``key``, dropping the oldest entry beyond ``_G_CACHE_SIZE``."""
    if len(_G_CACHE) >= _G_CACHE_SIZE:
        _G_CACHE.pop(next(iter(_G_CACHE)))
    _G_CACHE[key] = g


def _gather_key(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, config: IndirectConfig) -> tuple:
    import hashlib

    h = hashlib.sha1()
    for a in (vertices, faces, origin):
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest(), config.rays_per_point, config.seed, config.eps_m, config.max_edge_mm


class Radiosity:
    """The precomputed transport of one mesh (module docstring).

    ``rc``: an Open3D ``RaycastingScene`` of the mesh's vertices minus ``origin`` (float32, as the ray
    caster builds it); ``albedo``: (V, 3) linear diffuse albedo of the vertices (None: ``base_color``).
    The gather matrix depends only on the mesh, ``origin`` and the sampling knobs: it is built once per
    process for them and reused (the render stage's exposure meter, its metadata probe and an in-process
    worker share one build; ``cached`` says whether this instance reused it).
    """

    def __init__(self, rc, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, material: TissueMaterial,
                 albedo: np.ndarray | None, config: IndirectConfig, nthreads: int = 0) -> None:
        from ..geometry.open3d_adapter import o3d as open3d_module

        o3d = open3d_module()
        self._o3d = o3d
        self.rc = rc
        self.config = config
        self.nthreads = nthreads
        self.origin = np.asarray(origin, dtype=np.float64)
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        nv = len(self.vertices)
        #: vertices of the render mesh: the first ``n_render`` transport points are they (same indices)
        self.n_render = nv
        alb = (np.broadcast_to(np.asarray(material.base_color, dtype=np.float64), (nv, 3)) if albedo is None
               else np.asarray(albedo, dtype=np.float64))
        if alb.shape != (nv, 3):
            raise ValueError(f"indirect: albedo {alb.shape} for {nv} vertices")
        self.normals = vertex_normals_into_lumen(self.vertices, self.faces)
        #: every point has the same albedo (an untextured scene, e.g. the exposure meter's): the bounces are
        #: then one scalar power series per channel, E_n = s sum_k a^(k-1) G^k E_dir (:meth:`_bounce`)
        self.uniform_albedo = bool(nv == 0 or np.all(alb == alb[:1]))
        alb0 = np.array(alb[:1])
        if config.max_edge_mm > 0:                          # module docstring, "Transport mesh"
            from .refine import refine_long_edges

            self.vertices, self.faces, interp = refine_long_edges(self.vertices, self.faces, config.max_edge_mm * 1e-3)
            alb, nv, n = np.asarray(interp @ alb), len(self.vertices), np.asarray(interp @ self.normals)
            if self.uniform_albedo and self.n_render:   # not the interpolation's rounding (0.75 a + 0.25 a != a)
                alb = np.repeat(alb0, nv, axis=0)
            self.normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
            rc = o3d.t.geometry.RaycastingScene()
            rc.add_triangles(o3d.core.Tensor((self.vertices - self.origin).astype(np.float32)),
                             o3d.core.Tensor(self.faces.astype(np.uint32)))
            self.rc = rc
        mu = np.linspace(0.0, 1.0, 65)
        #: the specular lobe's directional albedo A(cos) at 65 cosines 0..1 (:func:`specular_albedo`)
        self.spec_table = specular_albedo(mu, material.roughness, material.specular)
        #: its mean over cosine-weighted incident light, 2 int A(mu) mu dmu: the share of bounced light the
        #: wet layer reflects (white), counted with the diffuse share in the transport (module docstring)
        self.spec_mean = float(np.trapz(2 * mu * self.spec_table, mu)) if config.glossy else 0.0
        spec_hemi = float(np.trapz(2 * mu * self.spec_table, mu))
        #: the diffuse base's hemispherical weight under the layering, 1 - 2 int A(mu) mu dmu
        self.diffuse_weight = 1.0 - spec_hemi
        self.rho = (alb * self.diffuse_weight + self.spec_mean).astype(np.float32)
        #: what a wall passes on to the others of the light it receives (module docstring, step 2): the
        #: layered ``rho`` with ``caustics``, else its albedo (Cycles without reflective caustics)
        self.rho_bounce = self.rho if config.caustics else alb.astype(np.float32)
        self._mu = mu
        self._alb = alb.astype(np.float32)
        fv = self.vertices[self.faces]
        #: triangle areas (F,), m^2, and the lumped mass of each vertex's hat function, int phi_j = sum A_f / 3
        self.face_area = 0.5 * np.linalg.norm(np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0]), axis=1)
        self.vertex_mass = np.bincount(self.faces.reshape(-1), np.repeat(self.face_area / 3, 3), minlength=nv)
        t0 = time.process_time()
        key = _gather_key(self.vertices, self.faces, self.origin, config)
        cached = _G_CACHE.get(key)
        #: True when the gather matrix came from this process's cache (built for the same mesh before)
        self.cached = cached is not None
        if cached is not None:
            self.G = cached
            self.build_cpu_s = time.process_time() - t0
            return
        self.G = self._gather(rc, o3d, nthreads)
        _remember_gather(key, self.G)
        self.build_cpu_s = time.process_time() - t0

    def _gather(self, rc, o3d, nthreads: int):
        """The sparse gather matrix G (module docstring), float32 CSR."""
        import scipy.sparse as sp

        config = self.config
        nv = len(self.vertices)
        k = config.rays_per_point
        rows, cols, vals = [], [], []
        fa = self.faces
        chunk = max(1, 2_000_000 // k)
        for s in range(0, nv, chunk):
            e = min(nv, s + chunk)
            n = self.normals[s:e]
            d = cosine_directions(n, k, config.seed + s).reshape(-1, 3)
            o = np.repeat(self.vertices[s:e] - self.origin + config.eps_m * n, k, axis=0)
            out = rc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32)),
                               nthreads=nthreads)
            prim = out["primitive_ids"].numpy().astype(np.int64)
            hit = np.isfinite(out["t_hit"].numpy())
            pn = out["primitive_normals"].numpy()
            # a front face seen from the lumen has its air->tissue normal along the ray
            hit &= np.einsum("ij,ij->i", pn, d.astype(np.float32)) > 0
            idx = np.flatnonzero(hit)
            uv = out["primitive_uvs"].numpy()[idx].astype(np.float64)
            w = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1) / k
            r = s + idx // k
            rows.append(np.repeat(r, 3))
            cols.append(fa[prim[idx]].reshape(-1))
            vals.append(w.reshape(-1))
        rows = np.concatenate(rows) if rows else np.zeros(0, np.int64)
        cols = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        vals = np.concatenate(vals) if vals else np.zeros(0)
        g = sp.csr_matrix((vals, (rows, cols)), shape=(nv, nv), dtype=np.float64)
        g.sum_duplicates()
        return g.astype(np.float32)

    # ------------------------------------------------------------------ per frame
    def bounce_albedo(self, cos_light: np.ndarray) -> np.ndarray:
        """(V, 3) float32 share of the tip light a vertex passes on to the other walls: :meth:`direct_albedo`
        with ``caustics``, else the albedo (module docstring, step 2)."""
        return self.direct_albedo(cos_light) if self.config.caustics else self._alb

    def direct_irradiance(self, pose: np.ndarray, light: TipLight) -> np.ndarray:
        """(V,) float32 irradiance (W/m^2) from the tip light at every vertex, camera-to-world ``pose``."""
        return self.direct(pose, light)[0]

    def direct_albedo(self, cos_light: np.ndarray) -> np.ndarray:
        """(V, 3) float32 share of the tip light a vertex re-emits, at its incidence cosine ``cos_light`` (V,):
        ``albedo (1 - A(n.l)) + A(n.l)`` (the wet layer's share only with ``glossy``; module docstring)."""
        a = np.interp(np.clip(cos_light, 0.0, 1.0), self._mu, self.spec_table).astype(np.float32)[:, None]
        return self._alb * np.float32(self.diffuse_weight) + (a if self.config.glossy else np.float32(0.0))

    def direct(self, pose: np.ndarray, light: TipLight) -> tuple[np.ndarray, np.ndarray]:
        """Direct irradiance (V,) float32 and the incidence cosine n.l (V,) at every vertex (0 where unlit)."""
        pose = np.asarray(pose, dtype=np.float64)
        lp = pose[:3, :3] @ np.asarray(light.offset_m, dtype=np.float64) + pose[:3, 3]
        axis = pose[:3, 2]
        lv = lp - self.vertices                                   # towards the light
        r2 = np.einsum("ij,ij->i", lv, lv)
        r = np.sqrt(np.maximum(r2, 1e-30))
        nl = np.einsum("ij,ij->i", self.normals, lv) / r
        cos_axis = -(lv @ axis) / r
        e = np.zeros(len(self.vertices), dtype=np.float32)
        lit = (nl > 0) & (cos_axis > 0 if light.spot_exponent > 0 else np.ones_like(nl, bool))
        idx = np.flatnonzero(lit)
        cos_l = np.where(lit, nl, 0.0).astype(np.float32)
        if idx.size == 0:
            return e, cos_l
        if self.config.shadows:
            o = self.vertices[idx] - self.origin + self.config.eps_m * self.normals[idx]
            d = (lp - self.origin) - o
            out = self.rc.cast_rays(self._o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32)),
                                    nthreads=self.nthreads)
            vis = out["t_hit"].numpy() >= 1.0 - 1e-4         # nothing between the point and the light
            idx = idx[vis]
        intensity = light.power_w / (4.0 * math.pi)
        val = (intensity * nl[idx] / np.maximum(r2[idx], 1e-12)).astype(np.float32)
        prof = light_profile(cos_axis[idx].astype(np.float32), r2[idx].astype(np.float32), light)
        if prof is not None:
            val = val * prof
        e[idx] = val
        return e, cos_l

    def point_irradiance(self, p: np.ndarray, n: np.ndarray, lp: np.ndarray, axis: np.ndarray,
                          light: TipLight) -> np.ndarray:
        """(N,) irradiance (W/m^2) of the tip light at ``lp`` on points ``p`` (N, 3) with unit normals ``n``
        into the lumen (as :meth:`direct`, with its shadow rays): the tip light at any surface point, as a
        path tracer needs it (benchmarks/realism_indirect_pt.py) and a fine quadrature of its power (tests)."""
        lv = lp - p
        r2 = np.einsum("ij,ij->i", lv, lv)
        r = np.sqrt(np.maximum(r2, 1e-30))
        nl = np.einsum("ij,ij->i", n, lv) / r
        cos_axis = -(lv @ axis) / r
        e = np.zeros(len(p))
        lit = (nl > 0) & (cos_axis > 0 if light.spot_exponent > 0 else True)
        idx = np.flatnonzero(lit)
        if idx.size and self.config.shadows:
            o = p[idx] - self.origin + self.config.eps_m * n[idx]
            d = (lp - self.origin) - o
            out = self.rc.cast_rays(self._o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32)),
                                    nthreads=self.nthreads)
            idx = idx[out["t_hit"].numpy() >= 1.0 - 1e-4]
        if idx.size == 0:
            return e
        val = light.power_w / (4.0 * math.pi) * nl[idx] / np.maximum(r2[idx], 1e-12)
        prof = light_profile(cos_axis[idx].astype(np.float32), r2[idx].astype(np.float32), light)
        e[idx] = val if prof is None else val * prof
        return e

    def indirect_irradiance(self, e_direct: np.ndarray, bounces: int | None = None,
                            cos_light: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) float32 irradiance of the light bounced 1..``bounces`` times (module docstring, step 2).
        ``cos_light`` (V,): the direct light's incidence cosines (:meth:`direct`); None: the direct light is
        re-emitted with the hemispherical ``rho`` as the bounced light (a uniform irradiance, e.g. a test)."""
        return self._bounce(e_direct, bounces, cos_light)[0]

    def _bounce(self, e_direct, bounces, cos_light) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Indirect irradiance after ``bounces`` and after ``bounces - 1`` steps, and the re-emitted direct light."""
        n = self.config.bounces if bounces is None else int(bounces)
        ed = np.asarray(e_direct, dtype=np.float32)[:, None]
        first = (self.rho if cos_light is None else self.direct_albedo(cos_light)) * ed   # (V, 3) as a mirror sees it
        e_ind = prev = np.zeros((len(ed), 3), dtype=np.float32)
        if self.uniform_albedo and (cos_light is None or not self.config.caustics) and len(ed):
            # one albedo everywhere: src = s E_dir and E_(n+1) = G (s E_dir + a E_n) give
            # E_n = s sum_(k=1..n) a^(k-1) G^k E_dir per channel, so each bounce is one single-column
            # product with G instead of three (tests/test_indirect.py: same values as the general loop)
            s = (self.rho_bounce if cos_light is None else self._alb)[0].astype(np.float32)
            a = self.rho_bounce[0].astype(np.float32)
            k, coef = ed[:, 0], s.copy()
            for _ in range(n):
                k = np.asarray(self.G @ k, dtype=np.float32)
                prev, e_ind = e_ind, e_ind + k[:, None] * coef
                coef = coef * a
            return e_ind, prev, first
        src = (self.rho_bounce if cos_light is None else self.bounce_albedo(cos_light)) * ed   # passed on to walls
        for _ in range(n):
            prev, e_ind = e_ind, _columns_product(self.G, src + self.rho_bounce * e_ind)
        return e_ind, prev, first

    def vertex_irradiance(self, pose: np.ndarray, light: TipLight) -> tuple[np.ndarray, np.ndarray]:
        """Direct (V,) and indirect (V, 3) irradiance at the vertices for a camera at ``pose``."""
        return self.frame(pose, light)[:2]

    def frame(self, pose: np.ndarray, light: TipLight) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Direct (V,) and indirect (V, 3) irradiance at the vertices for a camera at ``pose``, and the
        vertices' outgoing radiance (V, 3) as one glossy reflection sees it: the direct light re-emitted at
        its incidence and the light of one bounce fewer, ``(rho_dir E_dir + rho E_ind^(n-1)) / pi`` (a mirror
        ray at the pixel is itself a bounce, so the path keeps at most ``bounces`` bounces, as in Cycles)."""
        ed, cos_l = self.direct(pose, light)
        e_ind, prev, first = self._bounce(ed, None, cos_l)
        return ed, e_ind, (first + self.rho * prev) * np.float32(1 / math.pi)

    def mirror_radiance(self, origins: np.ndarray, dirs: np.ndarray, vertex_radiance: np.ndarray) -> np.ndarray:
        """(N, 3) float32 radiance arriving along world rays (``origins`` (N, 3) metres, ``dirs`` (N, 3)): the
        outgoing radiance of the wall each ray hits (``vertex_radiance`` (V, 3), e.g. :meth:`frame`'s third
        value, interpolated barycentrically); 0 where a ray escapes or hits a back face."""
        out = np.zeros((len(origins), 3), dtype=np.float32)
        if len(origins) == 0:
            return out
        d = np.asarray(dirs, dtype=np.float64)
        rays = np.concatenate([np.asarray(origins, dtype=np.float64) - self.origin, d], axis=1).astype(np.float32)
        res = self.rc.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.nthreads)
        hit = np.isfinite(res["t_hit"].numpy())
        hit &= np.einsum("ij,ij->i", res["primitive_normals"].numpy(), d.astype(np.float32)) > 0
        idx = np.flatnonzero(hit)
        if idx.size == 0:
            return out
        tri = self.faces[res["primitive_ids"].numpy()[idx].astype(np.int64)]
        uv = res["primitive_uvs"].numpy()[idx]
        lv = np.asarray(vertex_radiance, dtype=np.float32)
        w0 = (1 - uv[:, 0] - uv[:, 1])[:, None]
        out[idx] = w0 * lv[tri[:, 0]] + uv[:, :1] * lv[tri[:, 1]] + uv[:, 1:] * lv[tri[:, 2]]
        return out

