"""Realism (issue #15): airway coordinates and anatomy, scope light, per-frame exposure, hard views, `room realism`."""
from __future__ import annotations

import dataclasses
import functools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
from room_pipeline.errors import InputError
from room_pipeline.io.mesh import Mesh
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.exposure import ExposureParams, exposure_track, smooth_exposures
from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial
from room_pipeline.render.texture import MucosaTexture, airway_coordinates, anatomy_factor

from .test_raycast import look, tube

MM = 1e-3
ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "bronchoscopy_frames" / "brea_depth"
TEX = MucosaTexture()
CAM = CameraIntrinsics.from_fov(64, 64, 85.0)
# the EndoMapper scope light (the default is isotropic since session 9): LED 1.1 mm off the optical centre, spot mu 2.767 (EndoMapper)
LIGHT = TipLight(offset_m=(0.0, -1.1 * MM, 0.0), spot_exponent=2.767)
EXP = ExposureParams(target=0.43, min_ev=-12.0, max_ev=12.0)


def straight_graph(z0=-5 * MM, z1=200 * MM, generation=0) -> CentrelineGraph:
    z = np.linspace(z0, z1, 60)
    return CentrelineGraph([GraphBranch(0, -1, generation, np.stack([0 * z, 0 * z, z], 1), np.full(60, 5 * MM))])


def textured_scene(mesh, poses, graph=None, **kw) -> Scene:
    air = airway_coordinates(mesh.vertices, graph) if graph is not None else None
    return Scene(mesh, kw.pop("camera", CAM), np.asarray(poses), np.arange(len(poses)) * 0.1,
                 material=TissueMaterial(base_color=(0.8, 0.5, 0.54), texture=TEX), light=kw.pop("light", LIGHT),
                 vertex_airway=air, **kw)


@functools.cache
def default_indirect():
    """The render stage's default inter-reflection (conf/render: render.indirect_bounces, rays per point, seed).

    Composed once per process (a Hydra compose is ~0.3 CPU s; the result is a frozen dataclass, shared)."""
    from room_pipeline.config.compose import compose, section
    from room_pipeline.render.params import RenderParams, indirect_config

    return indirect_config(RenderParams.from_dict(dict(section(compose(), "render"))))


def render_auto(sc: Scene, indirect=None) -> tuple[list[np.ndarray], tuple]:
    """Every frame with the per-frame automatic exposure and the default inter-reflection (as the render stage
    does; ``indirect``: another :class:`IndirectConfig`)."""
    ind = default_indirect() if indirect is None else indirect
    evs = exposure_track(sc, EXP, indirect=ind)
    sc = dataclasses.replace(sc, film=dataclasses.replace(sc.film, frame_ev=evs))
    r = RaycastRenderer(sc, RaycastConfig(indirect=ind))
    return [r.render(i, {"rgb"}) for i in range(len(sc.poses))], evs


def test_hard_views_run_with_the_default_inter_reflection():
    assert default_indirect().bounces > 0


def assert_sane(outs, evs):
    for o in outs:
        assert np.all(np.isfinite(o["rgb_linear"]))
        rgb = o["rgb"]
        white = (rgb >= 250).any(-1).mean()
        assert white < 0.05, f"{white:.3f} of the frame clipped"
        assert rgb.mean() > 5, "all-black frame"
    assert all(EXP.min_ev <= e <= EXP.max_ev for e in evs)


# --------------------------------------------------------------------------- airway coordinates, anatomy


def test_airway_coordinates_of_a_straight_trachea():
    g = straight_graph()
    p = np.array([[0, -5 * MM, 10 * MM], [5 * MM, 0, 20 * MM], [0, 5 * MM, 30 * MM], [-5 * MM, 0, 30 * MM]])
    a = airway_coordinates(p, g)
    np.testing.assert_allclose(a[:, 0], [15, 25, 35, 35], atol=2.0)         # arc length from the start, mm
    np.testing.assert_allclose(a[:, 1], [1, 0, -1, 0], atol=1e-6)           # cos theta: 1 = posterior (RAS -y)
    np.testing.assert_allclose(np.abs(a[[1, 3], 2]), [1, 1], atol=1e-6)
    assert np.all(a[:, 3] == 0)
    empty = airway_coordinates(p, None)
    assert np.all(empty[:, 0] == 0) and np.all(empty[:, 1] == 1)
    assert airway_coordinates(np.zeros((0, 3)), g).shape == (0, 4)


def test_rings_in_the_trachea_not_on_the_membranous_wall_folds_deeper():
    s = np.linspace(0, 60, 601)
    ant = np.stack([s, -np.ones_like(s), 0 * s, 0 * s], 1)                  # anterior wall, trachea
    post = np.stack([s, np.ones_like(s), 0 * s, 0 * s], 1)                  # posterior (membranous) wall
    fa, fp = anatomy_factor(ant, TEX)[:, 0], anatomy_factor(post, TEX)[:, 0]
    assert fa.max() - fa.min() > 0.8 * TEX.ring_strength                    # rings show anteriorly ...
    per = np.fft.rfft(fa - fa.mean())
    assert np.argmax(np.abs(per)) == round(60 / TEX.ring_spacing_mm)        # ... every ring_spacing_mm
    assert np.ptp(fp) < 1e-9                                                # ... and not on the membranous wall
    th = np.linspace(-np.pi, np.pi, 721)
    deep = np.stack([0 * th + 3.0, np.cos(th), np.sin(th), 0 * th + 4], 1)  # generation 4: folds around
    fd = anatomy_factor(deep, TEX)[:, 0]
    spec = np.abs(np.fft.rfft(fd - fd.mean()))
    assert np.argmax(spec) == TEX.fold_count
    # colour with depth: redder (G, B lower relative to R) in deeper generations
    g0 = anatomy_factor(np.array([[3.0, 0, 1, 0]]), TEX)[0]
    g5 = anatomy_factor(np.array([[3.0, 0, 1, 5]]), TEX)[0]
    assert g5[1] / g5[0] < g0[1] / g0[0]


def test_appearance_is_per_shading_point_not_per_vertex():
    """On a coarse tube (long triangles, ~8 mm along the axis) the rings still show at their 6 mm spacing."""
    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=120 * MM, n_theta=24, n_z=16)
    g = straight_graph()
    pose = look([0, 4.0 * MM, 20 * MM], [0, 0, 1.0], down=(0, 1, 0))
    sc = textured_scene(mesh, [pose], g, camera=CameraIntrinsics.from_fov(96, 96, 85.0),
                        film=Film(exposure_ev=3.0))
    alb = RaycastRenderer(sc).albedo_per_pixel(0, RaycastRenderer(sc).cast(0))
    assert np.all(np.isfinite(alb))
    bake = RaycastRenderer(sc, RaycastConfig(per_pixel_texture=False))
    b = bake.albedo(bake.cast(0))
    # the per-pixel albedo has detail the vertex bake cannot (rings between the 8 mm vertex rows)
    hit = bake.cast(0).hit
    assert np.std(np.diff(alb[..., 1], axis=0)[hit[1:] & hit[:-1]]) > 1.5 * np.std(
        np.diff(b[..., 1], axis=0)[hit[1:] & hit[:-1]])


# --------------------------------------------------------------------------- light


def test_spot_profile_and_exponential_falloff():
    from room_pipeline.render.shading import light_profile

    iso = TipLight()
    assert light_profile(np.ones(3), np.ones(3), iso) is None
    spot = TipLight(spot_exponent=2.767)
    np.testing.assert_allclose(light_profile(np.array([1.0, 0.5, 0.0]), np.ones(3), spot),
                               [1.0, 0.5 ** 2.767, 0.0], rtol=1e-5)
    ex = TipLight(falloff="exponential", falloff_length_m=0.02)
    r = np.array([0.01, 0.02, 0.04])
    f = light_profile(np.ones(3), r * r, ex)
    np.testing.assert_allclose(f / (r * r), np.exp(-r / 0.02) / 0.02 ** 2, rtol=1e-4)   # I cos e^{-r/L} / L^2
    with pytest.raises(ValueError):
        TipLight(falloff="linear")


# --------------------------------------------------------------------------- exposure


def test_smoothing_is_causal_bounded_and_deterministic():
    ts = np.arange(50) * 0.1
    raw = np.where(np.arange(50) < 20, -2.0, 3.0)
    a = smooth_exposures(raw, ts, EXP)
    assert np.all(a[:20] == -2.0)
    assert np.all(np.diff(a[20:]) >= 0) and a[20] < 3.0 and abs(a[-1] - 3.0) < 0.01
    assert a.tobytes() == smooth_exposures(raw.copy(), ts, EXP).tobytes()
    clamp = smooth_exposures(np.array([50.0, -50.0]), np.array([0.0, 100.0]), EXP)
    assert clamp.tolist() == [EXP.max_ev, EXP.min_ev]
    assert smooth_exposures(raw, ts, dataclasses.replace(EXP, smoothing_s=0.0)).tolist() == raw.tolist()
    with pytest.raises(ValueError):
        ExposureParams(min_ev=1.0, max_ev=0.0)


def test_exposure_follows_the_scene_no_blowout_near_the_wall():
    """Approaching the wall the gain drops (a fixed first-frame exposure would blow the frame out)."""
    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=120 * MM)
    poses = [look([0, 0, 10 * MM], [0, 0, 1.0])] + [look([0, 4.5 * MM, 40 * MM], [0, 1.0, 0.3])] * 3
    sc = textured_scene(mesh, poses, straight_graph())
    sc.timestamps = np.arange(4) * 1.0                        # 1 s apart: the smoothing (0.3 s) settles
    outs, evs = render_auto(sc)
    assert evs[-1] < evs[0] - 1.0
    assert_sane(outs, evs)
    fixed = RaycastRenderer(dataclasses.replace(sc, film=Film(exposure_ev=evs[0])),
                            RaycastConfig(indirect=default_indirect())).render(3, {"rgb"})["rgb"]
    assert (fixed >= 250).any(-1).mean() > (outs[3]["rgb"] >= 250).any(-1).mean()


def test_meter_in_blocks_on_one_thread_is_the_one_process_meter_bit_for_bit():
    """The render stage meters frames on its workers (render/sequence.meter_block: contiguous blocks, one Open3D
    thread each) and smooths in the driver; that must be exposure_track's every-frame-here result, bit for bit."""
    from room_pipeline.render.exposure import ExposureMeter, raw_exposures

    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=120 * MM)
    poses = [look([0, 0, z * MM], [0, 0.2 * (z % 3 - 1), 1.0]) for z in (5, 15, 25, 35, 45)] + \
        [look([0, 4.5 * MM, 40 * MM], [0, 1.0, 0.3])]
    sc = textured_scene(mesh, poses, straight_graph())
    sc.timestamps = np.arange(len(poses)) * 0.1
    ind = default_indirect()
    raw, limit = raw_exposures(sc, EXP, 0, ind)
    blocks = [(0, 2), (2, 5), (5, 6)]
    meters = [ExposureMeter(sc, EXP, 1, ind) for _ in blocks]       # as separate workers would, one thread each
    got = [x for m, (a, b) in zip(meters, blocks) for x in (m.frame(i) for i in range(a, b))]
    assert [e for e, _ in got] == raw.tolist() and [h for _, h in got] == limit.tolist()
    track = tuple(float(x) for x in smooth_exposures(np.array([e for e, _ in got]), sc.timestamps, EXP,
                                                     np.array([h for _, h in got])))
    assert track == exposure_track(sc, EXP, indirect=ind)
    assert len(set(track)) > 1                                       # the frames differ: not a vacuous equality


# --------------------------------------------------------------------------- hard views


def test_camera_half_a_millimetre_from_the_wall():
    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=60 * MM)
    poses = [look([0, 4.5 * MM, 20 * MM], [0, 1.0, 0.0]), look([0, 4.5 * MM, 20 * MM], [0, 1.0, 0.2])]
    outs, evs = render_auto(textured_scene(mesh, poses, straight_graph()))
    assert_sane(outs, evs)


def test_looking_down_a_long_dark_bronchus():
    mesh = tube(radius=2 * MM, z0=-5 * MM, z1=300 * MM, n_z=200)
    poses = [look([0, 0, 0], [0, 0, 1.0])]
    outs, evs = render_auto(textured_scene(mesh, poses, straight_graph(z1=300 * MM, generation=5)))
    assert_sane(outs, evs)
    lum = outs[0]["rgb"].max(-1)
    h, w = lum.shape
    # the far lumen is dark, as in a real scope (the bounced light, on by default, reaches further down the tube
    # than the direct light: 0.4 % of this 64x64 frame is <= 10 levels with 8 bounces, > 1 % single-bounce)
    assert lum[h // 2 - 4:h // 2 + 4, w // 2 - 4:w // 2 + 4].min() <= 10 and np.median(lum) > 50
    assert (lum <= 10).mean() > 0.002


def bifurcation() -> tuple[Mesh, CentrelineGraph]:
    """A parent tube and two children meeting at a carina (open tubes; not watertight, fine for ray casting)."""
    parts, off = [], 0
    vs, fs = [], []
    for ang, z0, z1, r in ((0.0, -40 * MM, 0.0, 6 * MM), (0.5, 0.0, 40 * MM, 4 * MM), (-0.5, 0.0, 40 * MM, 4 * MM)):
        m = tube(radius=r, z0=z0, z1=z1, n_theta=48, n_z=40)
        v = m.vertices.copy()
        c, s = np.cos(ang), np.sin(ang)
        v = v @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T
        vs.append(v)
        fs.append(m.faces + off)
        off += len(v)
    mesh = Mesh(np.concatenate(vs), np.concatenate(fs))
    z = np.linspace(-40 * MM, 0, 20)
    trunk = GraphBranch(0, -1, 0, np.stack([0 * z, 0 * z, z], 1), np.full(20, 6 * MM))
    kids = []
    for bid, ang in ((1, 0.5), (2, -0.5)):
        t = np.linspace(0, 40 * MM, 20)
        kids.append(GraphBranch(bid, 0, 1, np.stack([np.sin(ang) * t, 0 * t, np.cos(ang) * t], 1),
                                np.full(20, 4 * MM)))
    return mesh, CentrelineGraph([trunk, *kids])


def test_bifurcation_close_up_and_a_fold_in_shadow():
    mesh, g = bifurcation()
    poses = [look([0, 0, -3 * MM], [0, 0, 1.0]),                            # carina 3 mm ahead
             look([0, 5.5 * MM, -20 * MM], [0, -0.05, 1.0])]                 # grazing along the wall: light barely reaches it
    outs, evs = render_auto(textured_scene(mesh, poses, g))
    assert_sane(outs, evs)


def fold_in_front_of_the_led() -> Mesh:
    """A 5 mm tube and a fold across it: a 0.3 mm thick shelf (y -0.9..-0.6 mm, |x| <= 4.9 mm, z 8..40 mm)
    between the scope's LED (1.1 mm below the lens, y -1.1 mm) and everything the lens at (0, 0, 10 mm)
    sees: its upper face and the wall above it get no direct light, only what bounces round the fold."""
    t = tube(radius=5 * MM, z0=-5 * MM, z1=80 * MM, n_z=60)
    xs, zs = np.linspace(-4.9 * MM, 4.9 * MM, 12), np.linspace(8 * MM, 40 * MM, 24)
    idx = np.arange(12 * 24).reshape(12, 24)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:], idx[1:, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    vs, fs, off = [t.vertices], [t.faces], len(t.vertices)
    for y, flip in ((-0.6 * MM, False), (-0.9 * MM, True)):
        X, Z = np.meshgrid(xs, zs, indexing="ij")
        vs.append(np.stack([X, np.full_like(X, y), Z], -1).reshape(-1, 3))
        fs.append((f[:, ::-1] if flip else f) + off)
        off += 12 * 24
    return Mesh(np.concatenate(vs), np.concatenate(fs))


def test_a_frame_in_the_shadow_of_a_fold():
    """Hard case: the whole view in a fold's shadow.  With the default renderer (no per-pixel shadow ray) the
    frame is sane; with ``RaycastConfig.direct_shadows`` the wall behind the fold loses its direct light
    (what Cycles renders), the gain control lifts the bounced light, and the frame is still sane."""
    sc = textured_scene(fold_in_front_of_the_led(), [look([0, 0, 10 * MM], [0, 0, 1.0])], straight_graph())
    ind = default_indirect()
    evs = exposure_track(sc, EXP, indirect=ind)
    outs, _ = render_auto(sc)
    assert_sane(outs, evs)
    fixed = dataclasses.replace(sc, film=Film(exposure_ev=0.0))
    lit = RaycastRenderer(fixed, RaycastConfig(indirect=ind)).render(0, {"rgb"})["rgb_linear"].mean(-1)
    r = RaycastRenderer(fixed, RaycastConfig(indirect=ind, direct_shadows=True))
    shadow = r.render(0, {"rgb"})["rgb_linear"].mean(-1)
    c = r.cast(0)
    blocked = r._in_shadow(0, c, r.camera_normals(0, c)[0])
    assert blocked.mean() > 0.9                               # the fold hides (nearly) the whole view from the LED
    assert np.all(shadow <= lit + 1e-9) and shadow.sum() < 0.5 * lit.sum()
    assert np.all(np.isfinite(shadow)) and shadow.max() > 0   # the bounced light remains
    # without the fold nothing the lens sees is hidden from the LED: the shadow rays change nothing
    open_tube = textured_scene(tube(radius=5 * MM, z0=-5 * MM, z1=80 * MM, n_z=60), fixed.poses, straight_graph(),
                               film=Film(exposure_ev=0.0))
    a = RaycastRenderer(open_tube, RaycastConfig(indirect=ind)).render(0, {"rgb"})["rgb"]
    b = RaycastRenderer(open_tube, RaycastConfig(indirect=ind, direct_shadows=True)).render(0, {"rgb"})["rgb"]
    assert np.abs(a.astype(int) - b).max() <= 1


def test_nothing_lit_gives_black_not_nan_and_bounded_exposure():
    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=60 * MM)
    sc = textured_scene(mesh, [look([0, 0, -50 * MM], [0, 0, -1.0])], straight_graph())   # looking away: no hit
    evs = exposure_track(sc, EXP, indirect=default_indirect())
    assert evs == (0.0,)
    out = RaycastRenderer(dataclasses.replace(sc, film=Film(frame_ev=evs)),
                          RaycastConfig(indirect=default_indirect())).render(0, {"rgb"})
    assert np.all(np.isfinite(out["rgb_linear"])) and out["rgb"].max() == 0


# --------------------------------------------------------------------------- room realism


def test_realism_statistics_and_floor(tmp_path):
    import cv2

    from room_pipeline import realism as R

    rng = np.random.default_rng(0)
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for i in range(6):
        im = np.clip(rng.normal(120, 20, (64, 64, 3)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(a / f"f{i}.png"), im)
        cv2.imwrite(str(b / f"f{i}.png"), np.clip(im.astype(int) + 60, 0, 255).astype(np.uint8))
    same = R.evaluate(a, a, size=64)
    assert same["real_vs_synth"]["dE76_mean_colour"] == 0 and same["real_vs_synth"]["L_hist_emd"] == 0
    assert same["real_vs_synth"]["noise_lsd_db"] == 0 and "real_vs_real" in same
    brighter = R.evaluate(a, b, size=64, noise=False)
    assert brighter["real_vs_synth"]["dE76_mean_colour"] > 10 and brighter["real_vs_synth"]["L_hist_emd"] > 10
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no frames"):
        R.frame_paths(tmp_path / "empty")
    with pytest.raises(InputError, match="no such folder"):
        R.frame_paths(tmp_path / "missing")


def test_room_realism_cli_errors(tmp_path):
    r = subprocess.run([sys.executable, "-m", "room_pipeline.cli", "realism", "--real", str(tmp_path / "nope")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().startswith("room: error:") and "nope" in r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.skipif(not REAL.is_dir(), reason="shared BREA-Depth frames not present (../shared/data)")
def test_real_vs_real_floor_on_the_shared_frames():
    from room_pipeline import realism as R

    res = R.evaluate(REAL, None, size=128, noise=False)
    f = res["real_vs_real"]
    assert 0 < f["dE76_mean_colour"] < 8 and 0 < f["L_hist_emd"] < 10
    assert res["real"]["clipped_fraction"] < 0.01


def test_report_shows_real_frames_beside_ours(tmp_path):
    import cv2

    from room_pipeline.report import sections as rh

    real, ds = tmp_path / "real", tmp_path / "ds"
    seq = ds / "patient_x" / "sequence_000" / "rgb_noisy"
    real.mkdir()
    seq.mkdir(parents=True)
    (seq.parent / "metadata").mkdir()
    (seq.parent / "metadata" / "render.json").write_text("{}")    # a rendered sequence (the report lists no other)
    rng = np.random.default_rng(1)
    for i in range(4):
        cv2.imwrite(str(real / f"r{i}.jpg"), rng.integers(0, 255, (48, 48, 3), dtype=np.uint8))
        cv2.imwrite(str(seq / f"frame_{i:04d}.png"), rng.integers(0, 255, (48, 48, 3), dtype=np.uint8))
    s = rh.section_realism(rh.ReportOptions(output_dir=ds, real_dir=real), [ds / "patient_x"])
    assert s.count("<img ") == 8 and "dE76_mean_colour" in s
    assert "not available" in rh.section_realism(rh.ReportOptions(output_dir=ds), [ds / "patient_x"])


def test_cycles_renders_the_same_scope_light_as_the_ray_caster():
    """Spot profile cos^mu (an IES profile in Cycles) and the LED offset: direct light, diffuse, the two agree;
    dropping the profile on one side costs well over 6 dB."""
    pytest.importorskip("bpy")
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings, linear_to_srgb8

    from .test_texture import _psnr

    mesh = tube(radius=5 * MM, z0=-5 * MM, z1=60 * MM, n_theta=80, n_z=80)
    cam = CameraIntrinsics.from_fov(64, 64, 85.0)
    poses = [look([1 * MM, 0.5 * MM, 0], [0.25, 0.1, 1.0])]
    st = CyclesSettings(samples=64, adaptive_threshold=0.0, denoise=True, max_bounces=0, threads=2,
                        filter_width=0.01)
    res = {}
    for name, light in (("spot", TipLight(radius_m=1e-6, offset_m=(0.0, -1.1 * MM, 0.0), spot_exponent=2.767)),
                        ("iso", TipLight(radius_m=1e-6, offset_m=(0.0, -1.1 * MM, 0.0)))):
        sc = Scene(mesh, cam, np.asarray(poses), np.zeros(1), light=light, film=Film(exposure_ev=4.0),
                   material=TissueMaterial(base_color=(0.8, 0.5, 0.54), specular=0.0))
        rc = RaycastRenderer(sc).render(0, {"rgb"})["rgb"]
        with CyclesRenderer(sc, st) as r:
            cy = linear_to_srgb8(r.render(0, ("rgb",))["rgb"])
        res[name] = (rc, cy)
    p_spot, p_cross = _psnr(*res["spot"]), _psnr(res["spot"][1], res["iso"][0])
    print(f"PSNR raycast vs Cycles with the spot profile: {p_spot:.1f} dB; vs isotropic raycast {p_cross:.1f} dB")
    assert p_spot > 35.0 and p_spot > p_cross + 6.0


def test_veiling_glare_keeps_energy_and_lifts_the_dark():
    from room_pipeline.render.shading import apply_response, veiling_glare

    x = np.zeros((8, 8, 3), np.float32)
    x[:4] = 0.5
    y = veiling_glare(x, 0.1)
    np.testing.assert_allclose(y.mean(axis=(0, 1)), x.mean(axis=(0, 1)), rtol=1e-6)   # energy kept
    assert y[6, 6, 0] > 0 and y[0, 0, 0] < 0.5
    assert veiling_glare(x, 0.0) is x
    a = apply_response(x, Film(veiling_glare=0.1))
    assert a[6, 6, 0] > 0 and apply_response(x, Film())[6, 6, 0] == 0
    with pytest.raises(ValueError):
        Film(veiling_glare=1.0)
