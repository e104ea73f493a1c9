"""Procedural airway-mucosa albedo: one appearance function of world position and airway coordinates.

:func:`mucosa_albedo` is evaluated **per shading point** by the ray caster
(at every hit: the exact world hit point and the airway coordinates
interpolated from the mesh vertices, :func:`airway_coordinates`), so detail
finer than a triangle (cartilage rings, vessels) is not lost on the long
triangles of a decimated tube.  Cycles evaluates the same function at every
shading point too: :mod:`room_pipeline.render.texture_osl` writes this
module's arithmetic (tables, fBm, vessels, anatomy factor) as an OSL shader
(equal to ~1e-5, float32; tests/test_texture.py).  The per-vertex bake
(:meth:`Scene.vertex_albedo <room_pipeline.render.scene.Scene.vertex_albedo>`)
remains for the ray caster's ``per_pixel_texture=False`` and Cycles'
``texture='vertex'``.  The pattern sticks to the surface (the same world
point has the same albedo in every view).

Anatomy (airway coordinates ``s`` = arc length from the trachea's start along
the centreline path, mm; ``theta`` = angle around the branch's centreline,
0 = posterior (RAS -y), rad; ``generation`` = branch generation, 0 = trachea)
    * cartilage rings (generations ``<= ring_max_generation``: trachea and main
      bronchi): paler bands every ``ring_spacing_mm`` of arc length (adult
      trachea: 16-20 C-shaped rings over 10-12 cm, ~6 mm apart), absent on the
      posterior membranous wall (``|theta| < membranous_half_angle_deg``);
    * longitudinal folds (deeper generations): ``fold_count`` stripes around
      the branch (``cos(fold_count theta)``), brightness ``fold_strength``;
    * colour with depth into the lung: each generation multiplies the albedo
      by ``(1 - depth_darkening)`` on G and B (redder, darker distally),
      at most ``depth_max_generation`` times.

Pattern (all lengths in millimetres of world space, RAS+)
    * mottling: fractal gradient noise (``mottle_octaves`` octaves, largest
      feature ``mottle_scale_mm``) scaling the albedo brightness, plus an
      independent noise of the same scale that shifts the colour between
      red and bluish-purple (``hue_strength``);
    * vessels: thin lines where a two-octave gradient noise of scale
      ``vessel_scale_mm`` crosses zero (``|n| < vessel_width``), blended
      towards ``vessel_color``; a slower noise makes vessels clear in some
      regions and faint in others.

The result is rescaled per channel so that its mean over space equals
``base_color`` (estimated once on a fixed set of sample points, independent
of the mesh), so the colour statistics of an untextured render are kept;
values are clipped to [0, 1].

Resolution of the vertex bake: evaluated at mesh *vertices* only and interpolated
linearly across triangles, so detail finer than the vertex spacing (about
0.35-1.2 mm on the lumen meshes; median edge 1.2 mm on the phantom) is not
represented: vessels narrower than that come out as ~1-vertex-wide, softened
lines.
"""
from __future__ import annotations

import dataclasses
import functools

import numpy as np

#: The 12 edge directions of a cube: Perlin's gradient set.
_GRADIENTS = np.array([[1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0],
                       [1, 0, 1], [-1, 0, 1], [1, 0, -1], [-1, 0, -1],
                       [0, 1, 1], [0, -1, 1], [0, 1, -1], [0, -1, -1]], dtype=np.float64)
_M32 = np.uint64(0xFFFFFFFF)


@dataclasses.dataclass(frozen=True)
class MucosaTexture:
    """Parameters of the procedural mucosa albedo (see the module docstring).

    enabled: False = the uniform ``base_color`` (no texture).
    seed: integer seed of every noise layer (same seed -> same bytes).
    mottle_scale_mm: size of the largest mottling blobs (noise lattice period), mm.
    mottle_octaves: octaves of the mottling noise (each half the size of the last).
    mottle_strength: standard deviation of the relative brightness modulation (0.2 = +-20 %).
    hue_strength: standard deviation of the red <-> blue shift (relative, on R and B in opposite senses).
    vessel_scale_mm: spacing of the vessel network (noise lattice period), mm.
    vessel_width: half-width of a vessel line in noise units; the line is about
        ``2 * vessel_width / 1.2 * vessel_scale_mm`` mm wide (1.2 ~ the noise's mean gradient per lattice cell).
    vessel_strength: blend weight towards ``vessel_color`` at a vessel's centre (0..1).
    vessel_color: linear RGB albedo of a vessel (dark red).
    ring_spacing_mm: cartilage ring period along the centreline arc length, mm.
    ring_width: fraction of a period covered by a ring (0..1).
    ring_strength: relative brightening of the albedo on a ring (cartilage is paler).
    ring_max_generation: rings in generations 0..this (0 trachea, 1 main bronchi); -1 = none.
    membranous_half_angle_deg: half-angle of the ring-free posterior membranous wall, deg.
    fold_count: longitudinal folds around a branch beyond the ringed generations.
    fold_strength: relative brightness amplitude of the folds.
    depth_darkening: per generation, the relative drop of G and B (redder distally).
    depth_max_generation: the darkening stops at this generation.
    """

    enabled: bool = True
    seed: int = 0
    mottle_scale_mm: float = 8.0
    mottle_octaves: int = 3
    mottle_strength: float = 0.15
    hue_strength: float = 0.06
    vessel_scale_mm: float = 6.0
    vessel_width: float = 0.10
    vessel_strength: float = 0.35
    vessel_color: tuple[float, float, float] = (0.42, 0.06, 0.08)
    ring_spacing_mm: float = 6.0
    ring_width: float = 0.4
    ring_strength: float = 0.25
    ring_max_generation: int = 1
    membranous_half_angle_deg: float = 50.0
    fold_count: int = 8
    fold_strength: float = 0.12
    depth_darkening: float = 0.04
    depth_max_generation: int = 6

    def __post_init__(self) -> None:
        for k in ("mottle_scale_mm", "vessel_scale_mm", "vessel_width"):
            if not getattr(self, k) > 0:
                raise ValueError(f"texture.{k} must be > 0, got {getattr(self, k)}")
        if not 1 <= self.mottle_octaves <= 8:
            raise ValueError(f"texture.mottle_octaves must be in 1..8, got {self.mottle_octaves}")
        for k in ("mottle_strength", "hue_strength"):
            if not 0 <= getattr(self, k) <= 1:
                raise ValueError(f"texture.{k} must be in [0, 1], got {getattr(self, k)}")
        if not 0 <= self.vessel_strength <= 1:
            raise ValueError(f"texture.vessel_strength must be in [0, 1], got {self.vessel_strength}")
        if not self.ring_spacing_mm > 0 or not 0 < self.ring_width < 1:
            raise ValueError("texture.ring_spacing_mm must be > 0 and texture.ring_width in (0, 1)")
        for k in ("ring_strength", "fold_strength", "depth_darkening"):
            if not 0 <= getattr(self, k) <= 1:
                raise ValueError(f"texture.{k} must be in [0, 1], got {getattr(self, k)}")
        if not 0 <= self.membranous_half_angle_deg <= 180:
            raise ValueError(f"texture.membranous_half_angle_deg must be in [0, 180], got {self.membranous_half_angle_deg}")
        if self.fold_count < 0 or self.depth_max_generation < 0 or self.ring_max_generation < -1:
            raise ValueError("texture.fold_count, depth_max_generation >= 0 and ring_max_generation >= -1 required")
        if len(self.vessel_color) != 3 or not all(0 <= float(x) <= 1 for x in self.vessel_color):
            raise ValueError(f"texture.vessel_color must be 3 values in [0, 1], got {self.vessel_color}")


def _mix32(h: np.ndarray) -> np.ndarray:
    """A 32-bit integer finaliser (xor-shift-multiply), on uint64 arrays holding 32-bit values."""
    h = h & _M32
    h ^= h >> np.uint64(16)
    h = (h * np.uint64(0x7FEB352D)) & _M32
    h ^= h >> np.uint64(15)
    h = (h * np.uint64(0x846CA68B)) & _M32
    h ^= h >> np.uint64(16)
    return h


def _layer_key(seed: int, layer: int) -> np.uint64:
    return np.uint64(int(_mix32(np.array([(int(seed) * 0x9E3779B1 + layer * 0x85EBCA77) & 0xFFFFFFFF],
                                         dtype=np.uint64))[0]))


@functools.lru_cache(maxsize=256)
def _perm_table(key: int) -> np.ndarray:
    """A permutation of 0..255 (repeated to 512 entries) drawn from ``key``: the lattice hash."""
    perm = np.random.default_rng(int(key)).permutation(256).astype(np.intp)
    return np.concatenate([perm, perm])


_GRAD32 = _GRADIENTS.astype(np.float32)
_GRAD_OF = np.arange(256) % 12


@functools.lru_cache(maxsize=256)
def _corner_tables(key: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The permutation (512,) and, per hash value ``h`` in 0..511, the x, y, z components (512,) float32 of the
    lattice gradient ``_GRAD32[_GRAD_OF[perm[h]]]``: three contiguous 1-D tables, so a corner's gradient is three
    ``take`` calls instead of a gather of (N, 3) rows whose columns are then read strided (the same values:
    :func:`gradient_noise`'s bytes did not change, tests/test_texture.py; 1.34x faster at load 2.7,
    ``python benchmarks/texture_speed.py``)."""
    perm = _perm_table(key)
    g = _GRAD32[_GRAD_OF[perm]]
    return perm, np.ascontiguousarray(g[:, 0]), np.ascontiguousarray(g[:, 1]), np.ascontiguousarray(g[:, 2])


def gradient_noise(p: np.ndarray, key: np.uint64) -> np.ndarray:
    """3-D gradient (Perlin) noise at points ``p`` (N, 3) in lattice units; float64 (N,), roughly in [-1, 1].

    Lattice gradients (one of the 12 cube-edge directions) from Perlin's
    permutation-table hash of the integer cell corner, the permutation drawn
    from ``key``; the lattice repeats every 256 cells (>= 256 x the feature
    size: far larger than an airway).  Quintic fade, so the noise is C2 and
    zero-mean.  Arithmetic in float32 on cell-local coordinates; the eight
    corners summed in a fixed order (x, then y, then z), so the bytes depend
    on nothing but ``p`` and ``key``.
    """
    p = np.asarray(p, dtype=np.float64)
    if len(p) == 0:
        return np.zeros(0)
    perm, gx, gy, gz = _corner_tables(int(key))
    i0 = np.floor(p)
    f = (p - i0).astype(np.float32)
    ii = i0.astype(np.int64) & 255
    c6, c15, c10 = np.float32(6.0), np.float32(15.0), np.float32(10.0)
    frac, fade, cell = [], [], []
    for k in range(3):                      # per axis, contiguous: offsets to the two corners, weights, indices
        fk = np.ascontiguousarray(f[:, k])
        wk = fk * fk * fk * (fk * (fk * c6 - c15) + c10)
        frac.append((fk, fk - 1))
        fade.append((1 - wk, wk))
        ik = np.ascontiguousarray(ii[:, k])
        cell.append((ik, ik + 1))
    (fx, fy, fz), (wx, wy, wz), (X, Y, Z) = frac, fade, cell
    out = np.zeros(len(p), dtype=np.float32)
    for dx in (0, 1):
        px = perm.take(X[dx])
        for dy in (0, 1):
            pxy = perm.take(px + Y[dy])
            wxy = wx[dx] * wy[dy]
            for dz in (0, 1):
                h = pxy + Z[dz]
                dot = gx.take(h) * fx[dx] + gy.take(h) * fy[dy] + gz.take(h) * fz[dz]
                out += (wxy * wz[dz]) * dot
    return out.astype(np.float64)


def _fbm(p: np.ndarray, octaves: int, key_seed: int, layer: int) -> np.ndarray:
    out = np.zeros(len(p))
    amp = 1.0
    for o in range(octaves):
        out += amp * gradient_noise(p * (2.0 ** o), _layer_key(key_seed, layer * 16 + o))
        amp *= 0.5
    return out


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


N_FIELDS = 4


def noise_fields(points_mm: np.ndarray, t: MucosaTexture, seed: int) -> np.ndarray:
    """The smooth noise fields (N, 4) float32 at points in mm: brightness fBm, hue fBm, vessel noise, vessel region.

    All four are C2 functions of position; the albedo is a pointwise function
    of them (:func:`albedo_from_fields`), so a renderer may evaluate them on a
    coarser grid and interpolate them before the (sharp) vessel threshold.
    """
    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(p), N_FIELDS), dtype=np.float32)
    pm = p / t.mottle_scale_mm
    out[:, 0] = _fbm(pm, t.mottle_octaves, seed, 1)
    out[:, 1] = _fbm(pm + 17.31, max(1, t.mottle_octaves - 1), seed, 2)
    pv = p / t.vessel_scale_mm
    out[:, 2] = gradient_noise(pv, _layer_key(seed, 3)) + 0.5 * gradient_noise(2.0 * pv, _layer_key(seed, 4))
    out[:, 3] = gradient_noise(pv / 3.0 + 5.17, _layer_key(seed, 5))
    return out


def _pattern(fields: np.ndarray, t: MucosaTexture) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised albedo pattern (N, 3) around a unit base colour and the vessel weight (N, 1)."""
    f = np.asarray(fields, dtype=np.float64)
    s_b, s_h = _std_of_fbm(t.mottle_octaves), _std_of_fbm(max(1, t.mottle_octaves - 1))
    b = 1.0 + t.mottle_strength * f[:, 0] / s_b
    h = t.hue_strength * f[:, 1] / s_h
    rgb = np.stack([b * (1.0 + h), b, b * (1.0 - h)], axis=1)
    line = 1.0 - _smoothstep(0.0, t.vessel_width, np.abs(f[:, 2]))
    region = _smoothstep(-0.25, 0.25, f[:, 3])                                  # where vessels show
    a = (t.vessel_strength * line * (0.35 + 0.65 * region))[:, None]
    return np.maximum(rgb, 0.0), a


def _raw_albedo(points_mm: np.ndarray, t: MucosaTexture, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return _pattern(noise_fields(points_mm, t, seed), t)


def anatomy_factor(airway: np.ndarray, t: MucosaTexture) -> np.ndarray:
    """Per-point multiplicative RGB factor (N, 3) of the airway anatomy (rings, folds, colour with depth).

    ``airway``: (N, 4) = arc length s (mm), cos theta, sin theta (theta about
    the centreline, 0 = posterior), generation (float; interpolated values are
    rounded).  See the module docstring.
    """
    a = np.asarray(airway, dtype=np.float64).reshape(-1, 4)
    s_mm, c, sn = a[:, 0], a[:, 1], a[:, 2]
    gen = np.rint(a[:, 3])
    norm = np.maximum(np.hypot(c, sn), 1e-9)
    c, sn = c / norm, sn / norm
    # rings: a smooth band of width ring_width per period, centred on phase 0
    ph = np.mod(s_mm / t.ring_spacing_mm, 1.0)
    dist = np.minimum(ph, 1.0 - ph)                                              # 0 .. 0.5 periods
    hw = 0.5 * t.ring_width
    ring = 1.0 - _smoothstep(0.6 * hw, hw, dist)
    # membranous wall: no cartilage within the posterior sector (smooth edge of 10 deg)
    ang = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))                          # 0 = posterior
    h = t.membranous_half_angle_deg
    cart = _smoothstep(h - 5.0, h + 5.0, ang)
    ringed = gen <= t.ring_max_generation
    fac = 1.0 + t.ring_strength * np.where(ringed, ring * cart, 0.0)
    if t.fold_count > 0:
        theta = np.arctan2(sn, c)
        fold = 0.5 * (1.0 + np.cos(t.fold_count * theta))
        fac = fac * (1.0 + t.fold_strength * np.where(ringed, 0.0, fold - 0.5) * 2.0)
    dk = (1.0 - t.depth_darkening) ** np.clip(gen, 0, t.depth_max_generation)
    out = np.stack([fac, fac * dk, fac * dk], axis=1)
    return out


def albedo_from_fields(fields: np.ndarray, t: MucosaTexture, seed: int, base_color,
                       airway: np.ndarray | None = None) -> np.ndarray:
    """The albedo (N, 3) float32 in [0, 1] from :func:`noise_fields` and optional airway coordinates."""
    base = np.asarray(base_color, dtype=np.float64).reshape(3)
    rgb, a = _pattern(fields, t)
    mean = _mean_pattern(t, int(seed), tuple(float(x) for x in base))
    rgb = rgb * (base * base / np.maximum(mean, 1e-9))                          # spatial mean -> base_color
    vess = np.asarray(t.vessel_color, dtype=np.float64) * (base / np.maximum(mean, 1e-9))
    if airway is not None:
        rgb = rgb * anatomy_factor(airway, t)
    alb = (1 - a) * rgb + a * vess
    return np.clip(alb, 0.0, 1.0).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _std_of_fbm(octaves: int) -> float:
    """Standard deviation of :func:`_fbm` (estimated once on fixed sample points)."""
    p = np.random.default_rng(12345).uniform(-50.0, 50.0, (20000, 3))
    return float(np.std(_fbm(p, octaves, 0, 1)))


@functools.lru_cache(maxsize=64)
def _mean_pattern(t: MucosaTexture, seed: int, base_color: tuple[float, float, float]) -> np.ndarray:
    """Spatial mean (3,) of the un-normalised albedo for ``base_color`` (fixed sample points, cached)."""
    p = np.random.default_rng(54321).uniform(-200.0, 200.0, (40000, 3))
    rgb, a = _raw_albedo(p, t, seed)
    alb = (1 - a) * rgb * np.asarray(base_color) + a * np.asarray(t.vessel_color)
    return alb.mean(axis=0)


def mucosa_albedo(points_world: np.ndarray, params: MucosaTexture, seed: int | None = None,
                  base_color: tuple[float, float, float] = (0.80, 0.38, 0.32),
                  airway: np.ndarray | None = None) -> np.ndarray:
    """Linear RGB albedo (N, 3) float32 in [0, 1] at world points ``points_world`` (N, 3), metres.

    The one appearance function of both renderers.  ``airway``: optional
    (N, 4) airway coordinates (:func:`anatomy_factor`); without them no
    rings/folds/depth colour.  ``seed`` overrides ``params.seed``.  The spatial
    mean of the noise pattern is ``base_color`` per channel (before the
    anatomy factor and clipping); ``params.enabled`` False returns
    ``base_color`` everywhere.  Deterministic: same inputs give the same bytes.
    """
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    base = np.asarray(base_color, dtype=np.float64).reshape(3)
    if not params.enabled:
        return np.broadcast_to(base.astype(np.float32), p.shape).copy()
    s = int(params.seed if seed is None else seed)
    return albedo_from_fields(noise_fields(p * 1000.0, params, s), params, s, base, airway)


def airway_coordinates(points_world: np.ndarray, graph) -> np.ndarray:
    """Airway coordinates (N, 4) float32 of world points (metres) from a centreline graph.

    Columns: arc length s (mm) from the start of the trachea along the path to
    the nearest centreline sample; cos and sin of the angle theta about that
    branch's centreline, measured from the posterior direction (RAS -y)
    projected normal to the branch (right-handed about the distal tangent);
    the branch generation.  No centreline: zeros (generation 0).
    """
    from scipy.spatial import cKDTree

    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(p), 4), dtype=np.float32)
    out[:, 1] = 1.0
    if graph is None or not graph.branches or len(p) == 0:
        return out
    pts, tans, arc, gens = [], [], [], []
    start: dict[int, float] = {}
    for b in sorted(graph.branches, key=lambda b: (b.generation, b.id)):
        s0 = start.get(b.id, 0.0)
        seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
        s = s0 + np.concatenate([[0.0], np.cumsum(seg)])
        for c in graph.children(b.id):
            start[c.id] = float(s[-1])
        t = np.gradient(b.points, axis=0)
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
        pts.append(b.points); tans.append(t); arc.append(s); gens.append(np.full(len(s), b.generation))
    pts, tans, arc, gens = (np.concatenate(x) for x in (pts, tans, arc, gens))
    _, idx = cKDTree(pts).query(p)
    t = tans[idx]
    r = p - pts[idx]
    r -= np.einsum("ij,ij->i", r, t)[:, None] * t
    post = np.array([0.0, -1.0, 0.0])[None, :] - (-t[:, 1])[:, None] * t    # posterior minus its tangential part
    pn = np.linalg.norm(post, axis=1, keepdims=True)
    alt = np.array([0.0, 0.0, 1.0])[None, :] - t[:, 2:3] * t                  # branch along y: use superior
    post = np.where(pn > 1e-6, post / np.maximum(pn, 1e-12), alt / np.maximum(np.linalg.norm(alt, axis=1, keepdims=True), 1e-12))
    lat = np.cross(t, post)
    rn = np.maximum(np.linalg.norm(r, axis=1), 1e-12)
    out[:, 0] = arc[idx] * 1000.0
    out[:, 1] = np.where(rn > 1e-12, np.einsum("ij,ij->i", r, post) / rn, 1.0)
    out[:, 2] = np.where(rn > 1e-12, np.einsum("ij,ij->i", r, lat) / rn, 0.0)
    out[:, 3] = gens[idx]
    return out


def vertex_albedo_area_mean(vertices: np.ndarray, faces: np.ndarray, params: MucosaTexture,
                            base_color: tuple[float, float, float], airway: np.ndarray | None = None,
                            n: int = 3) -> np.ndarray:
    """Per-vertex albedo (V, 3) float32: the appearance function's mean over each vertex's hat function.

    ``sum_T int_T lambda_v(x) albedo(x) dA / sum_T int_T lambda_v(x) dA`` over
    the triangles T around vertex v (lambda_v: its barycentric coordinate), by
    the centroids of the ``n * n`` congruent sub-triangles of every triangle
    (equal weights).  For the light transport on the mesh (the inter-reflection
    of render/indirect.py, whose irradiance is linear inside a triangle):
    a wall re-emits the light of its surroundings with their mean albedo, not
    with the value at one point (:meth:`Scene.vertex_albedo`, which aliases
    detail finer than the vertex spacing: vessels, ring edges).  ``vertices``
    in metres; ``airway``: optional (V, 4) vertex airway coordinates, interpolated
    barycentrically as the ray caster does per pixel.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not params.enabled:
        return np.broadcast_to(np.asarray(base_color, dtype=np.float32), v.shape).copy()
    # barycentrics (m, 3) of the sub-triangle centroids: upward (i + 1/3, j + 1/3) and downward (i + 2/3, j + 2/3)
    b = [((i + 1 / 3) / n, (j + 1 / 3) / n) for i in range(n) for j in range(n - i)]
    b += [((i + 2 / 3) / n, (j + 2 / 3) / n) for i in range(n - 1) for j in range(n - 1 - i)]
    uv = np.asarray(b)
    lam = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)             # (m, 3)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    pts = np.einsum("mk,fkc->fmc", lam, v[f]).reshape(-1, 3)
    air = None
    if airway is not None:
        a = np.asarray(airway, dtype=np.float64).reshape(-1, 4)
        air = np.einsum("mk,fkc->fmc", lam, a[f]).reshape(-1, 4)
    alb = mucosa_albedo(pts, params, base_color=base_color, airway=air).astype(np.float64).reshape(len(f), len(lam), 3)
    w = area[:, None, None] * lam[None, :, :]                                           # (F, m, 3 corners)
    num = np.zeros((len(v), 3))
    den = np.zeros(len(v))
    for k in range(3):
        np.add.at(num, f[:, k], np.einsum("fm,fmc->fc", w[:, :, k], alb))
        np.add.at(den, f[:, k], w[:, :, k].sum(axis=1))
    out = np.where(den[:, None] > 0, num / np.maximum(den, 1e-300)[:, None],
                   mucosa_albedo(v, params, base_color=base_color, airway=airway))
    return out.astype(np.float32)
