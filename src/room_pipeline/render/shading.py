"""The fast renderer's material and light model (pure numpy, float32).

It takes the parameters the Cycles backend gives a Principled BSDF and a
point light (:class:`~room_pipeline.render.scene.TissueMaterial`,
:class:`~room_pipeline.render.scene.TipLight`, :class:`~room_pipeline.render.scene.Film`)
and evaluates a single-bounce approximation of what Cycles renders.

Light
    A point light at ``TipLight.offset_m`` in the camera frame with radiant
    power ``P`` watts radiates the intensity ``I = P / (4 pi)`` W/sr (Cycles'
    convention for point lights).  Irradiance at a surface point at distance
    ``r``: ``E = I max(n.l, 0) / r^2`` (inverse-square falloff).  The light
    sits at (or next to) the camera, so everything the camera sees is lit: no
    shadow rays.

BRDF (dielectric Principled BSDF, metallic 0, no transmission / clearcoat / sheen)
    ``f = (1 - A(n.v)) base_color / pi  +  D G F / (4 (n.l) (n.v))`` (``base_color``
    replaced per pixel by a texture's albedo when one is given), with
    GGX distribution ``D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)``,
    ``a = roughness^2`` (Blender's remapping), Smith-GGX masking-shadowing in
    the separable Schlick form ``G = G1(n.l) G1(n.v)``, ``G1(x) = x / (x (1 - k) + k)``,
    ``k = a / 2``, and Schlick's Fresnel ``F = F0 + (1 - F0) (1 - v.h)^5`` with
    ``F0 = 0.08 * specular`` (Principled 'Specular' 0.5 -> F0 = 0.04, IOR 1.5).
    The specular lobe is white (specular tint 0): the wet-mucosa highlights.
    ``A(n.v)`` is the lobe's directional albedo (:func:`specular_albedo`, dielectric Fresnel): Blender's
    Principled BSDF (4.0+) scales the diffuse base under the specular layer by it, which darkens walls
    seen at grazing angles; with ``1 - F`` instead, the direct light of the default scene was 4-14 %
    brighter than Cycles' at the far, grazing walls (0-bounce check,
    ``python benchmarks/realism_indirect.py --check-direct``).

Camera response
    Linear pixel value = outgoing radiance ``f E`` times ``2**exposure_ev``,
    then the sRGB transfer function clipped to [0, 1] (Blender's 'Standard'
    view transform) and rounded to 8 bits.

What it leaves out (so Cycles images differ): indirect light
(inter-reflections brighten the far, dimly lit parts of a tube; the ray caster adds them with
:mod:`room_pipeline.render.indirect` when ``RaycastConfig.indirect.bounces`` > 0), subsurface
scattering (softens and reddens), the light's finite radius (``radius_m``:
softer, wider highlights; treated as a point here), Blender 4's energy
compensation of the multiscatter GGX and its layering of specular over
diffuse (approximated by the ``1 - F`` weight), sampling noise and denoising.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .scene import Film, TipLight, TissueMaterial

#: Rec. 709 / sRGB luminance weights (linear RGB)
LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
VIEW_TRANSFORMS = ("standard",)


def _radiance(nl, nv, nh, vh, r2, mask, material: TissueMaterial, light: TipLight,
              albedo: np.ndarray | None = None, light_scale: np.ndarray | None = None) -> np.ndarray:
    """The BRDF times the irradiance, from per-pixel cosines and squared light distance (float32)."""
    f32 = np.float32
    nl = np.clip(nl, 0.0, 1.0, dtype=f32)
    nv = np.clip(nv, f32(1e-4), 1.0, dtype=f32)
    nh = np.clip(nh, 0.0, 1.0, dtype=f32)
    intensity = f32(light.power_w / (4.0 * math.pi))
    irradiance = (intensity * nl) / np.maximum(r2, f32(1e-12))                 # E = I cos / r^2
    if light_scale is not None:                                                 # spot profile, exponential falloff
        irradiance = irradiance * light_scale
    a = f32(max(material.roughness, 1e-3) ** 2)
    a2 = a * a
    f0 = f32(0.08 * material.specular)
    if vh is None:                                                             # v = h: F = F0
        fres = f0
    else:
        vh = np.clip(vh, 0.0, 1.0, dtype=f32)
        fres = f0 + (1 - f0) * (1 - vh) ** 5
    dd = nh * nh * (a2 - 1) + 1
    D = a2 / (f32(math.pi) * dd * dd)
    k = a / 2
    # G / (4 nl nv) with G = G1(nl) G1(nv), G1(x) = x / (x (1 - k) + k): the nl nv cancel
    vis = f32(0.25) / ((nl * (1 - k) + k) * (nv * (1 - k) + k))
    ks = (D * vis * fres) * irradiance                                          # white specular lobe
    kd = (1 - specular_albedo_at(nv, material)) * irradiance                  # layering: 1 - A(n.v)
    if albedo is None:
        base = np.asarray(material.base_color, dtype=f32) / f32(math.pi)
        out = kd[..., None] * base
    else:                                                                      # per-pixel albedo (texture)
        out = (kd * f32(1 / math.pi))[..., None] * np.asarray(albedo, dtype=f32)
    out += ks[..., None]
    if mask is not None:
        out *= np.asarray(mask, dtype=f32)[..., None]
    return out


@functools.lru_cache(maxsize=16)
def _specular_albedo_table(roughness: float, specular: float) -> np.ndarray:
    return specular_albedo(np.linspace(0.0, 1.0, _A_NODES), roughness, specular).astype(np.float32)


_A_NODES = 129


def specular_albedo_at(cos_v: np.ndarray, material: TissueMaterial) -> np.ndarray:
    """The specular lobe's directional albedo A(n.v) (:func:`specular_albedo`), from a 129-entry table (float32)."""
    tab = _specular_albedo_table(float(material.roughness), float(material.specular))
    x = np.clip(np.asarray(cos_v, dtype=np.float32), 0.0, 1.0) * np.float32(_A_NODES - 1)
    i = np.minimum(x.astype(np.int32), _A_NODES - 2)
    t = x - i
    return tab[i] * (1 - t) + tab[i + 1] * t


def dielectric_fresnel(cos_i: np.ndarray, ior: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric of refractive index ``ior`` (from air), float64."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    g2 = ior * ior - 1 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    a = (g - c) / np.maximum(g + c, 1e-300)
    b = (c * (g + c) - 1) / (c * (g - c) + 1)
    return 0.5 * a * a * (1 + b * b)


def specular_albedo(cos_v: np.ndarray, roughness: float, specular: float, n: int = 64,
                    exact_fresnel: bool = True) -> np.ndarray:
    """Directional albedo of the specular lobe of :func:`_radiance` (GGX, separable Smith-Schlick
    ``G1(x) = x / (x (1 - k) + k)``, ``k = alpha / 2``, Schlick Fresnel with ``F0 = 0.08 specular``,
    ``alpha = roughness^2``): the fraction of uniform incident radiance the lobe reflects towards a viewer at
    ``cos_v`` to the normal -- and, by reciprocity, the fraction of light from that direction it takes.
    Blender's Principled BSDF (4.0+) layers the dielectric's specular over the diffuse base and scales the
    base by ``1 - A(n.v)`` so the pair conserves energy; the diffuse term here does the same.
    ``exact_fresnel``: the dielectric's Fresnel equations at the IOR of ``F0`` (as Blender; the highlight
    term of :func:`_radiance` keeps Schlick's form, which is F0 at the coaxial light's v = h), else Schlick.
    Deterministic quadrature over the GGX distribution of half vectors (midpoints of an ``n`` x ``2n``
    grid of its inverse CDF): ``A = E_h[F G v.h / (n.v n.h)]`` over half vectors whose mirrored light
    direction is above the surface.  Float64, the shape of ``cos_v``."""
    a = max(roughness, 1e-3) ** 2
    f0 = 0.08 * specular
    sf = math.sqrt(min(f0, 0.99))
    ior = (1 + sf) / (1 - sf)                  # F0 = ((ior - 1) / (ior + 1))^2: Principled 'Specular' 0.5 -> 1.5
    fresnel = lambda x: dielectric_fresnel(x, ior)  # noqa: E731
    k = a / 2
    u1 = (np.arange(n) + 0.5) / n
    u2 = (np.arange(2 * n) + 0.5) / (2 * n)
    th = np.arctan(a * np.sqrt(u1 / (1 - u1)))[:, None]
    ph = (2 * math.pi * u2)[None, :]
    hx, hz = np.sin(th) * np.cos(ph), np.cos(th) * np.ones_like(ph)
    cv = np.clip(np.asarray(cos_v, dtype=np.float64).reshape(-1), 1e-4, 1.0)
    out = np.empty(len(cv))
    g1 = lambda x: x / (x * (1 - k) + k)  # noqa: E731
    for j, c in enumerate(cv):
        s = math.sqrt(max(1 - c * c, 0.0))
        vh = s * hx + c * hz
        lz = 2 * vh * hz - c                     # l = 2 (v.h) h - v
        ok = (lz > 0) & (vh > 0)
        F = fresnel(vh) if exact_fresnel else f0 + (1 - f0) * (1 - np.clip(vh, 0, 1)) ** 5
        val = np.where(ok, F * g1(np.clip(lz, 0, 1)) * g1(c) * vh / (c * hz), 0.0)
        out[j] = float(val.mean())
    return out.reshape(np.shape(cos_v))


def shade_linear(points_cam: np.ndarray, normals_cam: np.ndarray, mask: np.ndarray | None,
                 material: TissueMaterial, light: TipLight, albedo: np.ndarray | None = None) -> np.ndarray:
    """Outgoing radiance (linear RGB, float32, (..., 3)) towards the camera.

    ``points_cam``: (..., 3) surface points in the camera frame (metres);
    ``normals_cam``: (..., 3) unit normals facing the camera; ``mask``: where
    there is a surface (elsewhere the result is 0); ``albedo``: optional
    per-pixel linear RGB albedo (..., 3) replacing ``material.base_color``
    in the diffuse term (a texture); float32 throughout.
    """
    f32 = np.float32
    p = np.asarray(points_cam, dtype=f32)
    n = np.asarray(normals_cam, dtype=f32)
    lp = np.asarray(light.offset_m, dtype=f32)
    dot = lambda x, y: np.einsum("...i,...i->...", x, y)  # noqa: E731
    pv = dot(p, p)
    v = p * (-1.0 / np.sqrt(np.maximum(pv, f32(1e-30))))[..., None]            # towards the camera
    lv = lp - p
    r2 = dot(lv, lv)
    l = lv * (1.0 / np.sqrt(np.maximum(r2, f32(1e-30))))[..., None]            # towards the light
    hv = l + v
    h = hv * (1.0 / np.sqrt(np.maximum(dot(hv, hv), f32(1e-30))))[..., None]
    return _radiance(dot(n, l), dot(n, v), dot(n, h), dot(v, h), r2, mask, material, light, albedo,
                     light_profile(-l[..., 2], r2, light))


def light_profile(cos_axis: np.ndarray, r2: np.ndarray, light: TipLight) -> np.ndarray | None:
    """Factor on the inverse-square irradiance: spot profile ``cos^mu`` and the exponential falloff option.

    ``cos_axis``: cosine between the optical axis (+z) and the direction from
    the light to the point; ``r2``: squared distance (m^2).  None when both are off.
    """
    f32 = np.float32
    out = None
    if light.spot_exponent > 0:
        out = np.clip(cos_axis, 0.0, 1.0, dtype=f32) ** f32(light.spot_exponent)
    if light.falloff == "exponential":
        L = f32(light.falloff_length_m)
        r2 = np.asarray(r2, dtype=f32)
        ex = r2 * np.exp(-np.sqrt(r2) / L) / (L * L)                         # (I cos e^{-r/L} / L^2) / (I cos / r^2)
        out = ex if out is None else out * ex
    return out


def shade_coaxial(cos_nv: np.ndarray, dist2: np.ndarray, mask: np.ndarray | None,
                  material: TissueMaterial, light: TipLight, albedo: np.ndarray | None = None,
                  cos_axis: np.ndarray | None = None) -> np.ndarray:
    """:func:`shade_linear` for a light at the camera centre (``offset_m`` = 0): then l = v = h.

    ``cos_nv``: (...) cosine between the normal and the direction to the
    camera; ``dist2``: squared distance to the camera (m^2); ``albedo`` as
    in :func:`shade_linear`.  Fewer operations
    on per-pixel scalars (the renderer's fast path); same values up to float32 rounding.
    """
    c = np.asarray(cos_nv, dtype=np.float32)
    d2 = np.asarray(dist2, dtype=np.float32)
    return _radiance(c, c, c, None, d2, mask, material, light, albedo, light_profile(cos_axis, d2, light)
                     if cos_axis is not None else light_profile(np.ones_like(c), d2, light))


def interreflection(direct: np.ndarray, albedo: np.ndarray | None, depth: np.ndarray, hit: np.ndarray,
                    material: TissueMaterial) -> np.ndarray:
    """Wall-to-wall light of a lumen (linear RGB (H, W, 3) float32) to add to the single-bounce ``direct``.

    A lumen is nearly closed: each wall point sees other walls in most of its
    hemisphere, and those walls at about its own depth are the brightest.  The
    indirect irradiance is modelled as ``F`` times the mean radiosity of the walls
    seen at a similar planar depth (``pi`` x their outgoing radiance, pixels
    within a Gaussian window of ``interreflection_window_m`` in depth), with
    every further bounce in the geometric series of the frame's mean albedo:

        L_ind = albedo * F * mean_z(L_direct) / (1 - F * mean(albedo))     (per channel)

    ``F = material.interreflection`` (0: nothing added) is fitted against Cycles'
    path tracing (``python benchmarks/cycles_reference.py --fit-interreflection``).
    ``albedo``: per-pixel albedo, None = ``material.base_color``.
    """
    f = float(material.interreflection)
    h, w = depth.shape
    out = np.zeros((h, w, 3), dtype=np.float32)
    hit = np.asarray(hit, dtype=bool)
    if f <= 0 or not hit.any():
        return out
    z = np.asarray(depth, dtype=np.float64)[hit]
    step = material.interreflection_window_m / 2
    idx = np.floor((z - z.min()) / step).astype(np.int64)
    nb = int(idx.max()) + 1
    x = np.arange(nb, dtype=np.float64)
    kern = np.exp(-0.5 * ((x[:, None] - x[None, :]) / 2.0) ** 2) if nb <= 2048 else None
    cnt = np.bincount(idx, minlength=nb).astype(np.float64)
    lin = np.asarray(direct, dtype=np.float32)[hit].astype(np.float64)
    alb = (np.broadcast_to(np.asarray(material.base_color, dtype=np.float64), lin.shape) if albedo is None
           else np.asarray(albedo, dtype=np.float64)[hit])
    rho = alb.mean(axis=0)
    for ch in range(3):
        sums = np.bincount(idx, weights=lin[:, ch], minlength=nb)
        if kern is not None:
            mean = (kern @ sums) / np.maximum(kern @ cnt, 1e-12)
        else:
            mean = sums / np.maximum(cnt, 1e-12)
        gain = f / max(1.0 - f * float(rho[ch]), 1e-3)
        out[..., ch][hit] = (alb[:, ch] * gain * mean[idx]).astype(np.float32)
    return out


def luminance(linear_rgb: np.ndarray) -> np.ndarray:
    return np.asarray(linear_rgb, dtype=np.float32) @ LUMINANCE


def auto_exposure_ev(linear_rgb: np.ndarray, mask: np.ndarray, film: Film) -> float:
    """EV mapping the ``film.auto_percentile`` luminance percentile of ``mask``-ed pixels to ``film.auto_target``.

    0.0 when nothing is lit.  Rounded to 1/1000 EV so the value prints and
    travels (to the Cycles backend, to metadata) exactly.
    """
    y = luminance(linear_rgb)[np.asarray(mask, dtype=bool)]
    y = y[y > 0]
    if y.size == 0:
        return 0.0
    ref = float(np.percentile(y, film.auto_percentile))
    if ref <= 0 or not math.isfinite(ref):
        return 0.0
    return round(math.log2(film.auto_target / ref), 3)


def _srgb_lut(n: int) -> np.ndarray:
    """8-bit sRGB code for linear values at the centres of ``n`` equal bins of [0, 1]."""
    x = (np.arange(n, dtype=np.float64) + 0.5) / n
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)


_LUT_BINS = 1 << 16
_LUT = _srgb_lut(_LUT_BINS)


def linear_to_srgb8(linear_rgb: np.ndarray, exposure_ev: float = 0.0, view_transform: str = "standard"
                    ) -> np.ndarray:
    """Scale by ``2**exposure_ev``, clip to [0, 1], sRGB-encode, 8 bits (uint8, same shape).

    The transfer function goes through a 65536-entry table (bins of 1/65536 of
    the linear range): at most one code value from the exact formula, at the
    rounding boundaries only.
    """
    if view_transform not in VIEW_TRANSFORMS:
        raise ValueError(f"view_transform must be one of {VIEW_TRANSFORMS}, got {view_transform!r}")
    scale = np.float32(2.0 ** exposure_ev * _LUT_BINS)
    idx = np.asarray(linear_rgb, dtype=np.float32) * scale
    np.nan_to_num(idx, copy=False, nan=0.0, posinf=_LUT_BINS - 1, neginf=0.0)
    np.clip(idx, 0, _LUT_BINS - 1, out=idx)
    return _LUT[idx.astype(np.int32)]


def veiling_glare(x: np.ndarray, g: float) -> np.ndarray:
    """``(1 - g) x + g mean(x)`` per channel over the image (float32; NaN-safe mean); ``g`` 0: ``x`` unchanged."""
    if g <= 0:
        return x
    m = np.nan_to_num(x.reshape(-1, x.shape[-1]).mean(axis=0, dtype=np.float64)).astype(np.float32)
    return x * np.float32(1.0 - g) + np.float32(g) * m


def apply_response(linear_rgb: np.ndarray, film: Film, exposure_ev: float = 0.0,
                   vignette: np.ndarray | None = None) -> np.ndarray:
    """Linear radiance -> 8-bit pixels through the film: exposure, vignetting, response curve, clipping.

    ``film.response`` 'srgb': :func:`linear_to_srgb8`; 'gamma': ``round(255 clip(x)^(1/gamma))``.
    ``vignette``: optional (H, W) factor.
    """
    x = np.asarray(linear_rgb, dtype=np.float32)
    if vignette is not None:
        x = x * np.asarray(vignette, dtype=np.float32)[..., None]
    x = veiling_glare(x * np.float32(2.0 ** exposure_ev), film.veiling_glare)
    exposure_ev = 0.0
    if film.response == "srgb":
        return linear_to_srgb8(x, exposure_ev, film.view_transform)
    y = np.clip(np.nan_to_num(x * np.float32(2.0 ** exposure_ev), nan=0.0), 0.0, 1.0)
    return np.rint(255.0 * y ** np.float32(1.0 / film.gamma)).astype(np.uint8)


def srgb8_exact(linear_rgb: np.ndarray, exposure_ev: float = 0.0) -> np.ndarray:
    """The same transform evaluated with the formula (float64): the reference for tests."""
    x = np.clip(np.asarray(linear_rgb, dtype=np.float64) * 2.0 ** exposure_ev, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)
