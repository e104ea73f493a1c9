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
    2. ``bounces`` Jacobi steps of ``E <- E_dir + G (rho E)`` per colour channel (``rho`` = the diffuse
       albedo of the points: the appearance's vertex albedo times ``1 - F0``, the Principled BSDF's
       dielectric weight at the tip light's coaxial half vector).  After ``n`` steps ``E`` holds paths of
       up to ``n`` bounces, as Cycles' ``max_bounces = n`` does; the indirect part is ``E - E_dir``.
    3. At each pixel, the indirect irradiance interpolated with the hit's barycentrics, times
       ``(1 - F0) albedo(x) / pi`` (the pixel's own albedo: the per-pixel appearance) is added to the
       direct radiance.

What it leaves out: glossy inter-reflection (the wet specular lobe's share of the bounced light, a few
per cent), the irradiance's variation inside a triangle beyond linear interpolation, and the texture's
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
    by one mirror ray every ``glossy_stride`` pixels.
    """

    bounces: int = 0
    rays_per_point: int = 64
    seed: int = 0
    shadows: bool = True
    eps_m: float = 1e-5
    glossy: bool = True
    glossy_stride: int = 2

    def __post_init__(self) -> None:
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


class Radiosity:
    """The precomputed transport of one mesh (module docstring).

    ``rc``: an Open3D ``RaycastingScene`` of the mesh's vertices minus ``origin`` (float32, as the ray
    caster builds it); ``albedo``: (V, 3) linear diffuse albedo of the vertices (None: ``base_color``).
    """

    def __init__(self, rc, vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, material: TissueMaterial,
                 albedo: np.ndarray | None, config: IndirectConfig, nthreads: int = 0) -> None:
        import scipy.sparse as sp

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
        self.normals = vertex_normals_into_lumen(self.vertices, self.faces)
        alb = (np.broadcast_to(np.asarray(material.base_color, dtype=np.float64), (nv, 3)) if albedo is None
               else np.asarray(albedo, dtype=np.float64))
        if alb.shape != (nv, 3):
            raise ValueError(f"indirect: albedo {alb.shape} for {nv} vertices")
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
        t0 = time.process_time()
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
        self.G = g.astype(np.float32)
        self.build_cpu_s = time.process_time() - t0

    # ------------------------------------------------------------------ per frame
    def direct_irradiance(self, pose: np.ndarray, light: TipLight) -> np.ndarray:
        """(V,) float32 irradiance (W/m^2) from the tip light at every vertex, camera-to-world ``pose``."""
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
        if idx.size == 0:
            return e
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
        return e

    def indirect_irradiance(self, e_direct: np.ndarray, bounces: int | None = None) -> np.ndarray:
        """(V, 3) float32 irradiance of the light bounced 1..``bounces`` times (module docstring, step 2)."""
        n = self.config.bounces if bounces is None else int(bounces)
        ed = np.repeat(np.asarray(e_direct, dtype=np.float32)[:, None], 3, axis=1)
        e = ed.copy()
        for _ in range(n):
            e = ed + self.G @ (self.rho * e)
        return e - ed

    def vertex_irradiance(self, pose: np.ndarray, light: TipLight) -> tuple[np.ndarray, np.ndarray]:
        """Direct (V,) and indirect (V, 3) irradiance at the vertices for a camera at ``pose``."""
        ed = self.direct_irradiance(pose, light)
        return ed, self.indirect_irradiance(ed)

    def mirror_radiance(self, origins: np.ndarray, dirs: np.ndarray, e_total: np.ndarray) -> np.ndarray:
        """(N, 3) float32 radiance arriving along world rays (``origins`` (N, 3) metres, ``dirs`` (N, 3)): the
        outgoing radiance ``rho E / pi`` of the wall each ray hits (``e_total`` (V, 3): the vertices'
        direct + indirect irradiance, interpolated barycentrically); 0 where a ray escapes or hits a back face."""
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
        lv = np.asarray(e_total, dtype=np.float32) * self.rho * np.float32(1 / math.pi)
        w0 = (1 - uv[:, 0] - uv[:, 1])[:, None]
        out[idx] = w0 * lv[tri[:, 0]] + uv[:, :1] * lv[tri[:, 1]] + uv[:, 1:] * lv[tri[:, 2]]
        return out

