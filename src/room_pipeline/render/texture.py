"""Procedural airway-mucosa albedo, defined in world space and baked per mesh vertex.

Both renderers read the same per-vertex albedo (:meth:`Scene.vertex_albedo
<room_pipeline.render.scene.Scene.vertex_albedo>`): the ray caster
interpolates it with the hit's barycentric coordinates, Cycles with a
POINT-domain colour attribute, so their RGB agrees and the pattern sticks to
the surface (the same world point has the same albedo in every view).

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

Resolution: the texture is evaluated at mesh *vertices* only and interpolated
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
    """

    enabled: bool = True
    seed: int = 0
    mottle_scale_mm: float = 8.0
    mottle_octaves: int = 3
    mottle_strength: float = 0.25
    hue_strength: float = 0.15
    vessel_scale_mm: float = 6.0
    vessel_width: float = 0.10
    vessel_strength: float = 0.55
    vessel_color: tuple[float, float, float] = (0.42, 0.06, 0.08)

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


def gradient_noise(p: np.ndarray, key: np.uint64) -> np.ndarray:
    """3-D gradient (Perlin) noise at points ``p`` (N, 3) in lattice units; float64 (N,), roughly in [-1, 1].

    The lattice gradients come from a hash of the integer cell corner and
    ``key``; quintic fade, so the noise is C2 and zero-mean.
    """
    p = np.asarray(p, dtype=np.float64)
    i0 = np.floor(p)
    f = p - i0
    i0 = i0.astype(np.int64)
    w = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)                     # quintic fade
    hx = [((i0[:, 0] + d) * 0x8DA6B343) & 0xFFFFFFFF for d in (0, 1)]
    hy = [((i0[:, 1] + d) * 0xD8163841) & 0xFFFFFFFF for d in (0, 1)]
    hz = [((i0[:, 2] + d) * 0xCB1AB31F) & 0xFFFFFFFF for d in (0, 1)]
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                h = _mix32((hx[dx] ^ hy[dy] ^ hz[dz]).astype(np.uint64) ^ key)
                g = _GRADIENTS[(h % np.uint64(12)).astype(np.intp)]
                dot = g[:, 0] * (f[:, 0] - dx) + g[:, 1] * (f[:, 1] - dy) + g[:, 2] * (f[:, 2] - dz)
                out += (wx * wy * wz) * dot
    return out


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


def _raw_albedo(points_mm: np.ndarray, t: MucosaTexture, seed: int) -> np.ndarray:
    """Unnormalised albedo pattern (N, 3) float64 around a unit base colour."""
    pm = points_mm / t.mottle_scale_mm
    bright = _fbm(pm, t.mottle_octaves, seed, 1)
    hue = _fbm(pm + 17.31, max(1, t.mottle_octaves - 1), seed, 2)
    s_b, s_h = _std_of_fbm(t.mottle_octaves), _std_of_fbm(max(1, t.mottle_octaves - 1))
    b = 1.0 + t.mottle_strength * bright / s_b
    h = t.hue_strength * hue / s_h
    rgb = np.stack([b * (1.0 + h), b, b * (1.0 - h)], axis=1)
    pv = points_mm / t.vessel_scale_mm
    n = gradient_noise(pv, _layer_key(seed, 3)) + 0.5 * gradient_noise(2.0 * pv, _layer_key(seed, 4))
    line = 1.0 - _smoothstep(0.0, t.vessel_width, np.abs(n))
    region = _smoothstep(-0.25, 0.25, gradient_noise(pv / 3.0 + 5.17, _layer_key(seed, 5)))   # where vessels show
    a = (t.vessel_strength * line * (0.35 + 0.65 * region))[:, None]
    return np.maximum(rgb, 0.0), a


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
                  base_color: tuple[float, float, float] = (0.80, 0.38, 0.32)) -> np.ndarray:
    """Linear RGB albedo (N, 3) float32 in [0, 1] at world points ``points_world`` (N, 3), metres.

    ``seed`` overrides ``params.seed``.  The spatial mean of the result is
    ``base_color`` per channel (before clipping); ``params.enabled`` False
    returns ``base_color`` everywhere.  Deterministic: same points, params and
    seed give the same bytes.
    """
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    base = np.asarray(base_color, dtype=np.float64).reshape(3)
    if not params.enabled:
        return np.broadcast_to(base.astype(np.float32), p.shape).copy()
    s = int(params.seed if seed is None else seed)
    rgb, a = _raw_albedo(p * 1000.0, params, s)
    alb = (1 - a) * rgb * base + a * np.asarray(params.vessel_color, dtype=np.float64)
    mean = _mean_pattern(params, s, tuple(float(x) for x in base))
    alb *= base / np.maximum(mean, 1e-9)
    return np.clip(alb, 0.0, 1.0).astype(np.float32)
