"""Procedural mucosa texture (render/texture.py): determinism, world-fixed, barycentrics, both backends."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from room_pipeline.errors import ConfigError
from room_pipeline.io.mesh import Mesh
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
from room_pipeline.render.scene import Film, TipLight, TissueMaterial
from room_pipeline.render.texture import MucosaTexture, mucosa_albedo
from room_pipeline.render.params import RenderParams, texture_params

from .test_raycast import look, scene, tube

MM = 1e-3
TEX = MucosaTexture()
BASE = (0.80, 0.50, 0.54)


def fine_tube() -> Mesh:
    """The test tube with ~0.4 mm vertex spacing (so the texture is resolved)."""
    return tube(radius=5 * MM, z0=-5 * MM, z1=40 * MM, n_theta=80, n_z=110)


def textured(mesh, poses, tex=TEX, **kw):
    return scene(mesh, poses, material=TissueMaterial(base_color=BASE, texture=tex), **kw)


# --------------------------------------------------------------------------- the pattern


def _gradient_noise_textbook(p, key):
    """Perlin's gradient noise with (N, 3) gradient rows per corner (the module's form before session 17), kept once
    in benchmarks/texture_speed.py (which times it): the reference the table-driven form must match bit for bit."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "texture_speed.py"
    spec = importlib.util.spec_from_file_location("texture_speed", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.gradient_noise_rows(p, key)


@pytest.mark.parametrize("scale", [0.5, 40.0, 3000.0])
def test_gradient_noise_matches_the_textbook_form_bit_for_bit(scale):
    """The lookup tables of :func:`gradient_noise` (three contiguous gradient components per hash value) change
    how the corners are gathered, not one value: the frames of every earlier run stay byte-identical."""
    from room_pipeline.render.texture import _layer_key, gradient_noise

    p = np.random.default_rng(7).uniform(-scale, scale, (20000, 3))
    p[:5] = [[0, 0, 0], [255.999, -0.0, 1e-9], [-1, -1, -1], [256, 512, -256], [0.5, 0.5, 0.5]]
    for layer in (1, 3, 5):
        key = _layer_key(11, layer)
        assert gradient_noise(p, key).tobytes() == _gradient_noise_textbook(p, key).tobytes()
    assert gradient_noise(np.zeros((0, 3)), _layer_key(0, 1)).shape == (0,)


def test_deterministic_and_seeded():
    p = np.random.default_rng(0).uniform(-0.05, 0.05, (5000, 3))
    a = mucosa_albedo(p, TEX, base_color=BASE)
    assert a.dtype == np.float32 and a.shape == (5000, 3)
    assert a.tobytes() == mucosa_albedo(p.copy(), MucosaTexture(), base_color=BASE).tobytes()
    assert a.tobytes() != mucosa_albedo(p, TEX, seed=1, base_color=BASE).tobytes()
    assert np.array_equal(mucosa_albedo(p, dataclasses.replace(TEX, seed=1), base_color=BASE),
                          mucosa_albedo(p, TEX, seed=1, base_color=BASE))
    assert np.all((a >= 0) & (a <= 1))
    # modulates around base_color: mean close, real variation, vessels darker
    # (R = 0.8 clips at 1 on ~20 % of points, which lowers its mean: the mean is base_color before clipping)
    np.testing.assert_allclose(a.mean(0)[1:], BASE[1:], atol=0.03)
    assert BASE[0] - 0.05 < a.mean(0)[0] <= BASE[0]
    assert np.all(a.std(0) > 0.05)
    off = mucosa_albedo(p, dataclasses.replace(TEX, enabled=False), base_color=BASE)
    assert np.array_equal(off, np.broadcast_to(np.float32(BASE), off.shape))


def test_pattern_is_smooth_at_its_scales_and_local():
    """Nearby points have close albedo (continuity); the value at a point does not depend on the others."""
    p = np.random.default_rng(1).uniform(-0.05, 0.05, (2000, 3))
    a = mucosa_albedo(p, TEX, base_color=BASE)
    b = mucosa_albedo(p + 1e-6, TEX, base_color=BASE)           # 1 micrometre away
    assert np.abs(a - b).max() < 0.01
    np.testing.assert_array_equal(mucosa_albedo(p[:10], TEX, base_color=BASE), a[:10])


def test_bad_parameters_and_config():
    with pytest.raises(ValueError, match="vessel_scale_mm"):
        MucosaTexture(vessel_scale_mm=0)
    with pytest.raises(ConfigError, match="render.texture.vesel"):
        RenderParams.from_dict({"texture": {"vesel": 1}})
    with pytest.raises(ConfigError, match="mottle_strength"):
        RenderParams.from_dict({"texture": {"mottle_strength": 3.0}})
    t = texture_params({"vessel_color": [0.5, 0.1, 0.1], "seed": 3})
    assert t.vessel_color == (0.5, 0.1, 0.1) and t.seed == 3 and t.enabled


# --------------------------------------------------------------------------- ray caster


def test_barycentric_interpolation_single_triangle():
    """Open3D's primitive_uvs (u, v) weigh vertices 1 and 2; the albedo at a hit is (1-u-v) a0 + u a1 + v a2."""
    cam = CameraIntrinsics.from_fov(40, 40, 60.0)
    v = np.array([[-0.02, -0.02, 0.05], [0.03, -0.01, 0.05], [-0.01, 0.03, 0.05]])
    sc = textured(Mesh(v, np.array([[0, 2, 1]])), [np.eye(4)])
    va = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)
    sc._albedo_cache = ((sc.material, id(sc.mesh.vertices), 3), va)     # known corner colours
    r = RaycastRenderer(sc)
    c = r.cast(0)
    alb = r.albedo(c)
    hit = c.hit
    assert hit.sum() > 100
    # the weights recovered from the world hit point by solving p = w0 v0 + w1 v1 + w2 v2
    X = r.render(0, {"world_points"})["world_points"][hit]
    A = np.stack([v[1] - v[0], v[2] - v[0]], 1)[:2]                  # the triangle lies in z = 0.05
    w12 = np.linalg.solve(A, (X[:, :2] - v[0, :2]).T).T
    want = np.column_stack([1 - w12.sum(1), w12])
    np.testing.assert_allclose(alb[hit], want, atol=1e-4)
    assert np.all(alb[~hit] == 0)


def test_texture_is_world_fixed():
    """Two cameras seeing the same surface point get the same albedo there."""
    mesh = fine_tube()
    poses = [look([1 * MM, 0, 0], [0.3, 0.1, 1.0]), look([-1.5 * MM, 1 * MM, 6 * MM], [-0.2, -0.2, 1.0])]
    r = RaycastRenderer(textured(mesh, poses, camera=CameraIntrinsics.from_fov(64, 64, 85.0)))
    c0, c1 = r.cast(0), r.cast(1)
    X0 = r.render(0, {"world_points"})["world_points"]
    a0, a1 = r.albedo(c0), r.albedo(c1)
    # project frame 0's hit points into camera 1 and sample (exact) at those sub-pixel positions
    m = c0.hit
    P1 = np.asarray(poses[1])
    Xc = (X0[m] - P1[:3, 3]) @ P1[:3, :3]
    cam = r.scene.camera
    uv = cam.project(Xc)
    d1, h1 = r.depth_at(P1, uv)
    vis = h1 & (np.abs(d1 - Xc[:, 2]) < 1e-6 + 1e-4 * Xc[:, 2])
    assert vis.sum() > 500
    # albedo at the same world points evaluated through camera 1's cast
    out = r._cast_rays(P1, np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                                            np.ones(len(uv))]).astype(np.float32))
    from room_pipeline.render.raycast import Cast

    n = len(uv)
    cc = Cast(depth=out["t_hit"].numpy().reshape(1, n), hit=vis.reshape(1, n),
              prim=out["primitive_ids"].numpy().reshape(1, n), uv=out["primitive_uvs"].numpy().reshape(1, n, 2))
    b = r.albedo(cc)[0][vis]
    np.testing.assert_allclose(b, a0[m][vis], atol=2e-3)
    assert a1[c1.hit].std(0).min() > 0.02                              # the texture is really there


def test_disabled_reproduces_untextured_rgb_exactly():
    mesh = tube()
    poses = [look([1 * MM, 0, 0], [0.2, 0.1, 1.0])]
    plain = RaycastRenderer(scene(mesh, poses, material=TissueMaterial(base_color=BASE))).render(0, {"rgb"})
    for tex in (None, dataclasses.replace(TEX, enabled=False)):
        off = RaycastRenderer(scene(mesh, poses, material=TissueMaterial(base_color=BASE, texture=tex)))
        assert off.scene.vertex_albedo() is None
        assert np.array_equal(off.render(0, {"rgb"})["rgb"], plain["rgb"])
    # also with a light off the camera centre (shade_linear path)
    light = TipLight(offset_m=(1 * MM, 0, 0))
    a = RaycastRenderer(scene(mesh, poses, material=TissueMaterial(base_color=BASE), light=light)).render(0, {"rgb"})
    b = RaycastRenderer(scene(mesh, poses, material=TissueMaterial(base_color=BASE, texture=MucosaTexture(
        enabled=False)), light=light)).render(0, {"rgb"})
    assert np.array_equal(a["rgb"], b["rgb"])
    on = RaycastRenderer(textured(mesh, poses)).render(0, {"rgb", "depth"})
    assert not np.array_equal(on["rgb"], plain["rgb"])


def test_uniform_texture_equals_base_colour_shading():
    """A per-pixel albedo equal to base_color everywhere gives the untextured radiance (float32 rounding)."""
    from room_pipeline.render.shading import shade_coaxial, shade_linear

    rng = np.random.default_rng(2)
    cos, d2 = rng.uniform(0.05, 1, (30, 30)), rng.uniform(1e-6, 1e-3, (30, 30))
    mat, light = TissueMaterial(base_color=BASE), TipLight()
    alb = np.broadcast_to(np.float32(BASE), (30, 30, 3))
    np.testing.assert_allclose(shade_coaxial(cos, d2, None, mat, light, alb), shade_coaxial(cos, d2, None, mat, light),
                               rtol=1e-6)
    p = np.column_stack([rng.uniform(-1, 1, (900, 2)) * 1e-2, rng.uniform(1e-3, 3e-2, 900)])
    n = -p / np.linalg.norm(p, axis=1, keepdims=True)
    np.testing.assert_allclose(shade_linear(p, n, None, mat, light, alb.reshape(-1, 3)),
                               shade_linear(p, n, None, mat, light), rtol=1e-6)


def test_texture_gives_orb_features():
    cv2 = pytest.importorskip("cv2")
    mesh = fine_tube()
    poses = [look([1 * MM, 0.5 * MM, 0], [0.25, 0.1, 1.0])]
    cam = CameraIntrinsics.from_fov(240, 240, 85.0)
    orb = cv2.ORB_create(nfeatures=2000, fastThreshold=5)
    # a finer pattern than the default (tuned to the phantom's ~1.2 mm vertex spacing): this tube has 0.4 mm
    fine = dataclasses.replace(TEX, vessel_scale_mm=3.0, vessel_width=0.12, vessel_strength=0.8, mottle_scale_mm=4.0)
    counts = []
    for tex in (None, fine):
        rgb = RaycastRenderer(scene(mesh, poses, camera=cam, material=TissueMaterial(base_color=BASE, texture=tex),
                                    film=Film(auto_target=0.43))).render(0, {"rgb"})["rgb"]
        counts.append(len(orb.detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None)))
    print("ORB keypoints untextured / textured:", counts)
    assert counts[1] > 5 * max(counts[0], 1), counts


# --------------------------------------------------------------------------- Cycles agreement


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * math.log10(255.0 ** 2 / mse) if mse > 0 else math.inf


def test_osl_appearance_equals_the_numpy_function_at_sample_points():
    """Cycles' per-shading-point albedo (the generated OSL shader, baked by Cycles at known points) equals
    :func:`mucosa_albedo` there: the same hash, permutation tables, fBm, vessels and anatomy factor.

    Both evaluate the float32 points; OSL works in float32 throughout (NumPy forms the lattice coordinates
    and the anatomy factor in float64), which is the whole remaining difference: <= 1e-5 at the noise
    layers' smooth parts, up to a few 1e-5 where a float32 rounding of the position or of the arc length
    meets a sharp edge (vessel threshold, ring edge: slopes of 15-20 per unit).  A wrong table, octave,
    constant or channel would differ by >= 1e-2."""
    pytest.importorskip("bpy")
    from room_pipeline.render.blender import osl_albedo_at

    rng = np.random.default_rng(7)
    n = 1500
    p = rng.uniform(-0.15, 0.15, (n, 3)).astype(np.float32)
    th = rng.uniform(-np.pi, np.pi, n)
    air = np.stack([rng.uniform(-20, 300, n), np.cos(th), np.sin(th), rng.integers(0, 8, n)], 1).astype(np.float32)
    p64 = p.astype(np.float64)
    smooth = dataclasses.replace(TEX, vessel_strength=0.0)
    d0 = np.abs(osl_albedo_at(p, smooth, BASE) - mucosa_albedo(p64, smooth, base_color=BASE))
    d1 = np.abs(osl_albedo_at(p, TEX, BASE) - mucosa_albedo(p64, TEX, base_color=BASE))
    d2 = np.abs(osl_albedo_at(p, TEX, BASE, air) - mucosa_albedo(p64, TEX, base_color=BASE, airway=air))
    seeded = dataclasses.replace(TEX, seed=3, mottle_octaves=5)
    d3 = np.abs(osl_albedo_at(p, seeded, BASE, air) - mucosa_albedo(p64, seeded, base_color=BASE, airway=air))
    print(f"max |OSL - NumPy|: noise only {d0.max():.2e}, + vessels {d1.max():.2e}, + anatomy {d2.max():.2e}, "
          f"seed 3 / 5 octaves {d3.max():.2e}; 99th percentile {np.percentile(d2, 99):.2e}")
    assert d0.max() <= 1e-5
    for d in (d1, d2, d3):
        assert np.mean(d.max(axis=1) > 1e-5) <= 0.02 and d.max() <= 1e-4


def test_cycles_matches_raycast_on_textured_tube():
    """Same textured Scene, direct light only, diffuse material: the two backends' 8-bit RGB agree.

    Specular 0 and 0 bounces reduce both backends to the Lambert term, so what is left is Cycles'
    sampling/denoising and pixel filter (0.01 px: the pixel centre, as the ray caster); the texture must
    add no disagreement (a mismatch of the albedo, e.g. vertex order or colour space, costs >10 dB).  Both
    the per-shading-point appearance (Cycles' OSL shader vs the ray caster's per-pixel evaluation, stride 1)
    and the per-vertex bake (both sides) are checked.
    """
    pytest.importorskip("bpy")
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings, linear_to_srgb8

    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=40 * MM, n_theta=24, n_z=30)      # coarse: ~1.3-1.5 mm edges
    cam = CameraIntrinsics.from_fov(64, 64, 85.0)
    poses = [look([1 * MM, 0.5 * MM, 0], [0.25, 0.1, 1.0])]
    film = Film(exposure_ev=4.0)
    light = TipLight(radius_m=1e-6)
    st = CyclesSettings(samples=64, adaptive_threshold=0.0, denoise=True, max_bounces=0, threads=2,
                        filter_width=0.01)
    res = {}
    for name, tex, mode in (("plain", None, "per_point"), ("tex", TEX, "per_point"), ("vtex", TEX, "vertex")):
        sc = scene(mesh, poses, camera=cam, light=light, film=film,
                   material=TissueMaterial(base_color=BASE, specular=0.0, texture=tex))
        cfg = RaycastConfig(per_pixel_texture=mode == "per_point", shading_stride=1)
        rc = RaycastRenderer(sc, cfg).render(0, {"rgb"})["rgb"]
        with CyclesRenderer(sc, dataclasses.replace(st, texture=mode)) as r:
            cy = linear_to_srgb8(r.render(0, ("rgb",))["rgb"])
        res[name] = (rc, cy)
    p_plain, p_tex, p_vtex = _psnr(*res["plain"]), _psnr(*res["tex"]), _psnr(*res["vtex"])
    p_cross = _psnr(res["tex"][1], res["vtex"][0])
    print(f"PSNR raycast vs Cycles: untextured {p_plain:.1f} dB, per-point texture {p_tex:.1f} dB, vertex bake "
          f"{p_vtex:.1f} dB; Cycles per-point vs raycast vertex bake {p_cross:.1f} dB")
    assert p_tex > 30.0 and p_vtex > 30.0
    assert p_tex > p_cross + 3.0          # Cycles sees the per-point detail the vertex bake lacks (5.4 dB)


def test_per_pixel_appearance_agrees_with_the_vertex_bake_on_a_fine_mesh():
    """The ray caster's per-shading-point appearance vs its vertex bake (what Cycles reads), on a tube whose
    vertex spacing (~0.4 mm) resolves the pattern: they agree closely; stride 2 (noise fields every other
    pixel, bilinear) stays close to stride 1."""
    mesh = fine_tube()
    poses = [look([1 * MM, 0.5 * MM, 0], [0.25, 0.1, 1.0])]
    sc = textured(mesh, poses, film=Film(exposure_ev=4.0), camera=CameraIntrinsics.from_fov(96, 96, 85.0))
    out = {}
    for name, cfg in (("bake", RaycastConfig(per_pixel_texture=False)), ("px1", RaycastConfig(shading_stride=1)),
                      ("px2", RaycastConfig(shading_stride=2))):
        out[name] = RaycastRenderer(sc, cfg).render(0, {"rgb"})["rgb"]
    assert _psnr(out["px1"], out["bake"]) > 28.0
    assert _psnr(out["px2"], out["px1"]) > 35.0
    assert np.all(np.isfinite(out["px1"]))


def test_vertex_albedo_area_mean_is_the_hat_weighted_mean():
    """The transport's vertex albedo: the appearance averaged over each vertex's hat function.  A constant
    appearance is kept exactly; on a fine mesh it is close to the point bake; on a coarse one it is smoother
    than the point samples (vessel lines and ring edges averaged, not aliased); RaycastConfig checks the mode."""
    from room_pipeline.render.texture import vertex_albedo_area_mean

    flat = dataclasses.replace(TEX, mottle_strength=0.0, hue_strength=0.0, vessel_strength=0.0)
    m = fine_tube()
    a = vertex_albedo_area_mean(m.vertices, m.faces, flat, BASE)
    assert a.dtype == np.float32 and a.shape == (m.n_vertices, 3)
    np.testing.assert_allclose(a, mucosa_albedo(m.vertices, flat, base_color=BASE), atol=1e-6)
    fine = vertex_albedo_area_mean(m.vertices, m.faces, TEX, BASE)
    point = mucosa_albedo(m.vertices, TEX, base_color=BASE)
    assert np.median(np.abs(fine - point)) < 0.01
    c = tube(radius=5 * MM, z0=-5 * MM, z1=40 * MM, n_theta=16, n_z=12)            # ~2-4 mm edges
    mean_c = vertex_albedo_area_mean(c.vertices, c.faces, TEX, BASE)
    point_c = mucosa_albedo(c.vertices, TEX, base_color=BASE)
    assert mean_c.std(axis=0).mean() < point_c.std(axis=0).mean()
    assert abs(float(mean_c.mean()) - float(point_c.mean())) < 0.05
    with pytest.raises(ValueError, match="transport_albedo"):
        RaycastConfig(transport_albedo="vertex")
