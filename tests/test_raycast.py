"""Fast renderer (Open3D ray casting): geometric agreement of the modalities, flow, shading, robustness."""
from __future__ import annotations

import math

import numpy as np
import pytest

from room_pipeline.io.mesh import Mesh
from room_pipeline.io.ply import read_ply
from room_pipeline.render import flow as fm
from room_pipeline.render.camera import CameraIntrinsics, look_at
from room_pipeline.render.raycast import (MODALITIES, RaycastConfig, RaycastRenderer, decode_relative_depth16,
                                          relative_depth16, write_point_cloud)
from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial
from room_pipeline.render.shading import linear_to_srgb8, shade_coaxial, shade_linear, specular_albedo, srgb8_exact

MM = 1e-3
CAM = CameraIntrinsics.from_fov(120, 120, 85.0)
ALL = set(MODALITIES)


# --------------------------------------------------------------------------- fixtures


def tube(radius=5 * MM, z0=-5 * MM, z1=60 * MM, n_theta=48, n_z=40, wobble=0.0) -> Mesh:
    """Open cylinder along +z, faces wound so normals point outward (from the lumen into the wall)."""
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    zs = np.linspace(z0, z1, n_z)
    r = radius * (1 + wobble * np.sin(3 * th)[None, :] * np.cos(zs / (7 * MM))[:, None])
    v = np.stack([r * np.cos(th)[None, :], r * np.sin(th)[None, :], np.broadcast_to(zs[:, None], r.shape)], -1)
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return Mesh(v.reshape(-1, 3), faces)


def quad(z, half=0.2, centre=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    x, y = centre
    v = np.array([[x - half, y - half, z], [x + half, y - half, z], [x + half, y + half, z], [x - half, y + half, z]])
    return v, np.array([[0, 2, 1], [0, 3, 2]])


def look(eye, forward, down=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose at ``eye`` looking along ``forward`` (OpenCV: x right, y down, z forward)."""
    return look_at(eye, forward, down)


def scene(mesh, poses, **kw) -> Scene:
    return Scene(mesh, kw.pop("camera", CAM), np.asarray(poses), np.arange(len(poses)) * 0.1, **kw)


def finite_everywhere(out: dict) -> None:
    for k, a in out.items():
        if np.issubdtype(np.asarray(a).dtype, np.floating):
            assert np.all(np.isfinite(a)), k


def tilt(T: np.ndarray, deg_x: float, deg_y: float) -> np.ndarray:
    rx, ry = math.radians(deg_x), math.radians(deg_y)
    Rx = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    Ry = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ Rx @ Ry
    return out


# --------------------------------------------------------------------------- geometry


def test_point_cloud_reprojects_onto_depth_exactly(tmp_path):
    mesh = tube(wobble=0.15)
    T = tilt(look([1 * MM, -0.5 * MM, 0.0], [0, 0, 1]), 8, -5)
    r = RaycastRenderer(scene(mesh, [T]))
    out = r.render(0, {"point_cloud", "depth", "rgb"})
    hit = out["hit"]
    assert hit.mean() > 0.5 and not hit.all()           # the open far end shows nothing
    p, px = out["point_cloud"].astype(np.float64), out["point_cloud_pixels"]
    assert len(p) == hit.sum()
    depth_at = out["depth"][px[:, 1], px[:, 0]]
    assert np.array_equal(out["point_cloud"][:, 2], depth_at)          # z is the depth, bit for bit
    uv = CAM.project(p)
    assert np.max(np.abs(uv - px) / CAM.width) < 1e-6
    # world points back in camera t are the same points
    wp = r.render(0, {"world_points"})["world_points"][hit]
    cam_pts = (wp - T[:3, 3]) @ T[:3, :3]
    assert np.max(np.abs(cam_pts - p)) < 1e-9 + 1e-7 * np.max(np.abs(p))
    # the PLY holds the same numbers
    write_point_cloud(tmp_path / "pc.ply", out, frame_index=0, pose=T)
    v, _ = read_ply(tmp_path / "pc.ply")
    assert list(v) == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert np.array_equal(np.stack([v["x"], v["y"], v["z"]], 1), out["point_cloud"])
    assert np.array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), out["rgb"][hit])
    assert b"frame: OpenCV camera" in (tmp_path / "pc.ply").read_bytes()[:600]


def test_depth_matches_analytic_cylinder():
    """Camera on the axis of a fine cylinder: depth = r / sqrt(x^2 + y^2) along each ray (facet error only)."""
    radius = 4 * MM
    mesh = tube(radius=radius, n_theta=720, n_z=4, z1=200 * MM)
    out = RaycastRenderer(scene(mesh, [look([0, 0, 0], [0, 0, 1])])).render(0, {"depth"})
    rays = CAM.pixel_rays()
    rho = np.hypot(rays[..., 0], rays[..., 1])
    m = out["hit"] & (rho > 0.2)
    expect = radius / rho[m]
    chord = 1 - math.cos(math.pi / 720)                 # facets sit inside the circle by at most this fraction
    assert np.all(out["depth"][m] <= expect * (1 + 1e-6))
    assert np.all(out["depth"][m] >= expect * (1 - chord - 1e-6))


@pytest.mark.parametrize("smooth", [True, False])
def test_normals_unit_and_facing_the_camera(smooth):
    mesh = tube(wobble=0.2)
    T = tilt(look([2 * MM, 1 * MM, 2 * MM], [0, 0, 1]), 20, 25)
    out = RaycastRenderer(scene(mesh, [T]), RaycastConfig(smooth_normals=smooth)).render(0, {"normals"})
    n, hit = out["normals"], out["hit"]
    assert n.dtype == np.float32 and n.shape == (120, 120, 3)
    assert np.max(np.abs(np.linalg.norm(n[hit], axis=1) - 1)) < 1e-5
    assert np.all(np.einsum("ij,ij->i", n[hit], CAM.pixel_rays()[hit]) < 0)
    assert np.all(n[~hit] == 0)
    if not smooth:        # flat normals are the face normals, flipped: perpendicular to the cylinder axis
        nw = n[hit] @ T[:3, :3].T
        assert np.abs(nw[:, 2]).max() < 0.25          # wobble tilts them a little


def test_segmentation_from_face_labels():
    mesh = tube()
    labels = (np.arange(mesh.n_faces) // 96) % 5 + 1
    T = look([0, 0, 0], [0, 0.3, 1])
    out = RaycastRenderer(scene(mesh, [T], face_labels=labels)).render(0, {"segmentation"})
    hit, prim, seg = out["hit"], out["primitive_ids"], out["segmentation"]
    assert seg.dtype == np.int32
    assert np.array_equal(seg[hit], labels[prim[hit]])
    assert np.all(seg[~hit] == -1) and np.all(prim[~hit] == -1)
    out2 = RaycastRenderer(scene(mesh, [T])).render(0, {"segmentation"})
    assert np.array_equal(out2["segmentation"], np.where(hit, 0, -1))


def test_relative_depth_normalisation():
    mesh = tube()
    out = RaycastRenderer(scene(mesh, [look([0, 0, 0], [0, 0.2, 1])])).render(0, {"depth", "relative_depth"})
    rel, rng, d, hit = out["relative_depth"], out["relative_depth_range"], out["depth"], out["hit"]
    assert rel.dtype == np.uint16
    assert np.all(rel[~hit] == 0) and rel[hit].min() == 1 and rel[hit].max() == 65535
    assert rng[0] == pytest.approx(d[hit].min()) and rng[1] == pytest.approx(d[hit].max())
    back = decode_relative_depth16(rel, rng)
    inv_step = (1 / rng[0] - 1 / rng[1]) / 65534
    assert np.max(np.abs(1 / back[hit] - 1 / d[hit])) <= 0.51 * inv_step + 1e-9
    assert np.argmax(rel) == np.argmin(np.where(hit, d, np.inf))       # nearest = largest value
    empty, r0 = relative_depth16(np.zeros((3, 3)), np.zeros((3, 3), bool))
    assert not empty.any() and not r0.any()


# --------------------------------------------------------------------------- flow


def test_flow_pure_translation_matches_analytic():
    D = 20 * MM
    v, f = quad(D)
    mesh = Mesh(v, f)
    T0 = look([0, 0, 0], [0, 0, 1])
    for t in ([0.5 * MM, 0, 0], [0, -0.3 * MM, 0], [0.2 * MM, 0.1 * MM, 2 * MM]):
        T1 = T0.copy()
        T1[:3, 3] = t                                      # camera moves by t (its axes = world axes)
        out = RaycastRenderer(scene(mesh, [T0, T1])).render(0, {"flow", "depth"})
        assert np.allclose(out["depth"], D, rtol=1e-6)
        u, vv = np.meshgrid(np.arange(120.0), np.arange(120.0))
        z1 = D - t[2]
        eu = CAM.fx * ((u - CAM.cx) / CAM.fx * D - t[0]) / z1 + CAM.cx - u
        ev = CAM.fy * ((vv - CAM.cy) / CAM.fy * D - t[1]) / z1 + CAM.cy - vv
        assert np.max(np.abs(out["flow"][..., 0] - eu)) < 1e-3
        assert np.max(np.abs(out["flow"][..., 1] - ev)) < 1e-3
        inside = (u + eu >= 0) & (u + eu <= 119) & (vv + ev >= 0) & (vv + ev <= 119)
        assert np.array_equal(out["flow_valid"], inside)


def _flow_scene(config=None):
    mesh = tube(wobble=0.15)
    T0 = tilt(look([0.8 * MM, -0.4 * MM, 0.0], [0, 0, 1]), 6, -4)
    T1 = tilt(T0, 1.5, 2.0)
    T1[:3, 3] = T0[:3, 3] + T0[:3, :3] @ np.array([0.15 * MM, 0.1 * MM, 0.8 * MM])
    return RaycastRenderer(scene(mesh, [T0, T1]), config), T0, T1


def test_warping_frame_t1_by_the_flow_reproduces_the_depth():
    r, T0, T1 = _flow_scene()
    o0 = r.render(0, {"flow", "depth", "segmentation"})
    o1 = r.render(1, {"depth", "segmentation"})
    valid = o0["flow_valid"]
    assert valid.mean() > 0.5
    rep = fm.reproject(o0["depth"], o0["hit"], CAM, T0, T1)
    assert np.array_equal(rep.flow, o0["flow"])
    # exact: a ray through p' = p + flow from camera t+1 hits at depth z_{t+1}
    uv1 = (np.stack(np.meshgrid(np.arange(120.0), np.arange(120.0)), -1) + o0["flow"])[valid]
    d1, hit1 = r.depth_at(T1, uv1)
    assert hit1.all()
    assert np.max(np.abs(d1 - rep.z1[valid])) < 1e-6
    # the warping check on the depth map: exact where p' sees one triangle (1/z affine there)
    res, m = fm.warp_residual(o0["depth"], o0["hit"], o1["depth"], o1["hit"], o0["flow"], valid, CAM, T0, T1)
    u1 = np.floor(rep.uv1[..., 0]).astype(int).clip(0, 118)
    v1 = np.floor(rep.uv1[..., 1]).astype(int).clip(0, 118)
    p1 = o1["primitive_ids"]
    same = (p1[v1, u1] == p1[v1, u1 + 1]) & (p1[v1, u1] == p1[v1 + 1, u1]) & (p1[v1, u1] == p1[v1 + 1, u1 + 1])
    planar = m & same
    assert planar.sum() > 0.3 * valid.sum()
    assert np.max(np.abs(res[planar])) < 1e-6
    # across mesh edges: the interpolation error only (large on the coarse tube seen at grazing angles)
    rel = np.abs(res[m]) / rep.z1[m]
    assert np.median(rel) < 1e-4 and np.percentile(rel, 99) < 5e-3 and rel.max() < 2e-2
    # warp_backward of any image agrees with the depth sampling on planar pixels (up to 1/z vs z interpolation)
    wz = fm.warp_backward(o1["depth"], o0["flow"])
    assert np.median(np.abs(wz[planar] - rep.z1[planar])) < 1e-6


def test_flow_occlusion_detected_and_modes_agree():
    """A small square in front of a wall; the camera slides sideways: points hidden at t+1 are invalid."""
    vb, fb = quad(30 * MM)
    vf, ff = quad(10 * MM, half=2 * MM)
    mesh = Mesh(np.vstack([vb, vf]), np.vstack([fb, ff + 4]))
    T0 = look([0, 0, 0], [0, 0, 1])
    T1 = T0.copy()
    T1[:3, 3] = [1.5 * MM, 0, 0]
    outs = {}
    for mode in ("depth", "raycast"):
        r = RaycastRenderer(scene(mesh, [T0, T1]), RaycastConfig(flow_occlusion=mode))
        outs[mode] = r.render(0, {"flow", "depth"})
    o = outs["raycast"]
    rep = fm.reproject(o["depth"], o["hit"], CAM, T0, T1)
    hidden = rep.in_view & ~o["flow_valid"]
    assert hidden.sum() > 50                                   # background strip behind the square at t+1
    assert np.all(o["depth"][hidden] > 25 * MM)                # only background points get hidden
    agree = (outs["depth"]["flow_valid"] == o["flow_valid"]).mean()
    assert agree > 0.99
    # the fast mode errs on the safe side: never valid where the exact one says hidden
    assert not np.any(outs["depth"]["flow_valid"] & hidden)


def test_last_frame_has_no_flow():
    r, _, _ = _flow_scene()
    out = r.render(1, {"flow"})
    assert not out["flow_valid"].any() and not out["flow"].any()


# --------------------------------------------------------------------------- robustness


def test_grazing_and_long_tube_produce_no_nan_or_inf():
    mesh = tube(radius=3 * MM, z0=-2 * MM, z1=80 * MM, n_z=60)
    poses = [
        look([0.3 * MM, 0, 0], [0, 0, 1]),                      # down a long straight tube
        tilt(look([2.8 * MM, 0, 5 * MM], [0, 0, 1]), 0, 6),     # 0.2 mm from the wall, grazing it
        look([2.95 * MM, 0, 10 * MM], [1, 0, 0]),               # 0.05 mm (< near) facing the wall
        look([0, 0, 40 * MM], [0, 0, -1]),                      # looking back out of the entrance
    ]
    r = RaycastRenderer(scene(mesh, poses))
    for i in range(len(poses)):
        out = r.render(i, ALL)
        finite_everywhere(out)
        hit = out["hit"]
        assert np.all(out["depth"][hit] >= CAM.near) and np.all(out["depth"][hit] <= CAM.far)
        assert np.all(out["depth"][~hit] == 0) and np.all(out["normals"][~hit] == 0)
        assert np.all(out["rgb"][~hit] == 0) and np.all(out["segmentation"][~hit] == -1)
        assert np.all(out["relative_depth"][~hit] == 0) and not out["flow_valid"][~hit].any()
        if i == 0:
            d = out["depth"][hit]
            assert d.min() < 3 * MM and d.max() > 50 * MM and (~hit).sum() > 0
        if i == 2:                                              # the wall is clipped by the near plane
            assert not hit.any()


def test_far_clip_marks_no_hit():
    mesh = tube(radius=3 * MM, z1=200 * MM)
    cam = CameraIntrinsics.from_fov(120, 120, 85.0, far=40 * MM)
    out = RaycastRenderer(scene(mesh, [look([0, 0, 0], [0, 0, 1])], camera=cam)).render(0, {"depth"})
    assert out["depth"].max() <= 40 * MM and (~out["hit"]).sum() > 0


def test_only_requested_modalities_are_computed(monkeypatch):
    import room_pipeline.render.raycast as rc

    r, _, _ = _flow_scene(RaycastConfig())
    r._exposure_ev = 0.0
    calls = []
    monkeypatch.setattr(rc, "shade_coaxial", lambda *a, **k: calls.append("shade") or np.zeros((120, 120, 3), np.float32))
    monkeypatch.setattr(rc.flowmod, "reproject", lambda *a, **k: calls.append("flow"))
    out = r.render(0, {"depth"})
    assert set(out) == {"hit", "depth"} and calls == [] and r.cast_count == 1
    assert set(r.timings) == {"cast"}
    out = r.render(0, {"normals"})
    assert set(out) == {"hit", "normals"} and calls == [] and r.cast_count == 1   # cast reused
    out = r.render(0, {"rgb"})
    assert set(out) == {"hit", "rgb", "rgb_linear"} and calls == ["shade"]
    with pytest.raises(ValueError, match="unknown modalities"):
        r.render(0, {"albedo"})
    with pytest.raises(IndexError):
        r.render(2, {"depth"})


def test_flow_reuses_the_next_frames_cast():
    r, _, _ = _flow_scene()
    r.render(0, {"flow", "depth"})
    r.render(1, {"flow", "depth"})
    assert r.cast_count == 2


# --------------------------------------------------------------------------- shading


def test_shading_model():
    mat, light = TissueMaterial(), TipLight()
    # coaxial fast path == general model with the light at the camera
    rng = np.random.default_rng(0)
    p = rng.uniform([-5e-3, -5e-3, 2e-3], [5e-3, 5e-3, 30e-3], (500, 3))
    v = -p / np.linalg.norm(p, axis=1, keepdims=True)
    n = v + rng.normal(0, 0.4, p.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[np.einsum("ij,ij->i", n, v) < 0] *= -1
    a = shade_linear(p, n, None, mat, light)
    b = shade_coaxial(np.einsum("ij,ij->i", n, v), np.einsum("ij,ij->i", p, p), None, mat, light)
    assert np.allclose(a, b, rtol=1e-4, atol=1e-6)
    # inverse-square falloff at normal incidence; Lambert + specular at normal incidence
    z = np.array([5e-3, 10e-3])
    L = shade_coaxial(np.ones(2), z ** 2, None, mat, light)
    assert L[0] / L[1] == pytest.approx([4, 4, 4], rel=1e-5)
    E = light.power_w / (4 * math.pi) / z[0] ** 2
    f0 = 0.08 * mat.specular
    alpha = mat.roughness ** 2
    spec = 1 / (math.pi * alpha ** 2) * f0 / 4               # D(1) G(1,1)=1 F0 / (4 * 1 * 1)
    a1 = float(specular_albedo(np.array(1.0), mat.roughness, mat.specular))   # diffuse under the layer: 1 - A(n.v)
    assert a1 == pytest.approx(f0, abs=2e-3)
    assert L[0] == pytest.approx((1 - a1) * np.array(mat.base_color) / math.pi * E + spec * E, rel=1e-4)
    # the specular lobe makes normal incidence much brighter than oblique (wet highlight), diffuse alone would be cos
    Lo = shade_coaxial(np.array([1.0, 0.5]), np.full(2, z[0] ** 2), None, mat, light)
    assert Lo[0, 1] / Lo[1, 1] > 4
    # rougher -> weaker highlight
    rough = shade_coaxial(np.ones(1), z[:1] ** 2, None, TissueMaterial(roughness=0.8), light)
    assert rough[0, 1] < L[0, 1]
    # the sRGB table is within one code of the formula, exactly 0 and 255 at the ends
    x = np.concatenate([np.linspace(0, 1.2, 20001), [0.0, 1.0, 5.0]]).astype(np.float32)
    assert np.max(np.abs(linear_to_srgb8(x).astype(int) - srgb8_exact(x).astype(int))) <= 1
    assert linear_to_srgb8(np.float32([0.0, 1.0, np.inf, np.nan])).tolist() == [0, 255, 255, 0]


def test_exposure_fixed_and_auto():
    mesh = tube()
    poses = [look([0, 0, 0], [0, 0.1, 1]), look([0, 0, 20 * MM], [0, 0.1, 1])]
    r = RaycastRenderer(scene(mesh, poses, film=Film(exposure_ev=None, auto_reference_frame=1)))
    ev = r.exposure_ev
    out = r.render(1, {"rgb"})
    from room_pipeline.render.shading import luminance
    y = luminance(out["rgb_linear"])[out["hit"]]
    assert np.percentile(y, 95) == pytest.approx(0.8, rel=1e-2)
    # fixed for the sequence: rendering another frame first does not change it
    r2 = RaycastRenderer(scene(mesh, poses, film=Film(exposure_ev=None, auto_reference_frame=1)))
    r2.render(0, {"rgb"})
    assert r2.exposure_ev == ev
    r3 = RaycastRenderer(scene(mesh, poses, film=Film(exposure_ev=ev + 1)))
    lin3 = r3.render(1, {"rgb"})["rgb_linear"]
    assert np.allclose(lin3, 2 * out["rgb_linear"], rtol=1e-5)
    assert r3.metadata()["exposure_ev"] == ev + 1


def test_look_at_is_a_right_handed_opencv_pose_even_when_down_is_parallel():
    for fwd, down in (([0.0, 0.0, 1.0], [0.0, 1.0, 0.0]), ([1.0, 2.0, -0.5], [0.3, -1.0, 0.2]),
                      ([0.0, 1.0, 0.0], [0.0, 2.0, 0.0]),                        # down parallel to forward
                      ([1.0, 0.0, 0.0], [-3.0, 0.0, 0.0])):                      # ... and both along world x
        T = look_at([1.0, 2.0, 3.0], fwd, down)
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 2], np.array(fwd) / np.linalg.norm(fwd), atol=1e-12)
        np.testing.assert_array_equal(T[:3, 3], [1.0, 2.0, 3.0])
    # the image's down axis (camera y) leans toward the requested down direction
    assert look_at([0, 0, 0], [0, 0, 1], [0.2, 1.0, 0.0])[:3, 1] @ [0.2, 1.0, 0.0] > 0


# --------------------------------------------------------------------------- Open3D without its viewer


def test_open3d_loads_without_its_viewer_which_still_loads_on_demand():
    """``open3d_adapter.o3d()`` defers ``open3d.visualization`` (dash, plotly, IPython: most of ``import open3d``'s
    CPU): a fresh process that casts rays never imports them, and the viewer, asked for, is the whole package."""
    import subprocess
    import sys

    code = r"""
import sys, numpy as np
from room_pipeline.geometry.open3d_adapter import MeshScene, o3d
s = MeshScene(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), np.array([[0, 1, 2]]))
assert s.distance(np.array([[0.2, 0.2, 1.0]])).tolist() == [1.0]
assert not {"dash", "plotly", "IPython"} & set(sys.modules), sorted({"dash", "plotly", "IPython"} & set(sys.modules))
import open3d, open3d.visualization as vis
assert o3d() is open3d and vis is open3d.visualization and callable(vis.draw_geometries)
assert "dash" in sys.modules and callable(vis.draw_plotly) and vis.gui is sys.modules["open3d.visualization.gui"]
print(" ".join(sorted(n for n in dir(vis) if not n.startswith("__"))))
"""
    deferred = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert deferred.returncode == 0, deferred.stderr
    plain = subprocess.run([sys.executable, "-c", "import open3d.visualization as v; "
                            "print(' '.join(sorted(n for n in dir(v) if not n.startswith('__'))))"],
                           capture_output=True, text=True)
    assert plain.returncode == 0, plain.stderr
    assert deferred.stdout == plain.stdout


@pytest.mark.parametrize("k", [1, 2, 3, 4])
@pytest.mark.parametrize("shape", [(600, 600), (37, 53)])
def test_upsample_bilinear_is_map_coordinates_bit_for_bit(k, shape):
    """The texture's noise fields are interpolated from every k-th pixel by :func:`upsample_bilinear`: the same
    bytes as SciPy's ``map_coordinates(order=1, mode='nearest')`` at ``(y / k, x / k)`` (what the ray caster called
    before), on values spanning 25 orders of magnitude and both signs, edge rows and columns clamped."""
    from scipy.ndimage import map_coordinates

    from room_pipeline.render.raycast import upsample_bilinear

    h, w = shape
    gh, gw = -(-h // k), -(-w // k)
    rng = np.random.default_rng(k * 1000 + h)
    coarse = (rng.standard_normal((gh, gw, 4)) * np.exp(rng.uniform(-40, 15, (gh, gw, 4)))).astype(np.float32)
    yy, xx = np.mgrid[:h, :w].reshape(2, -1)
    coords = np.stack([yy / k, xx / k]).astype(np.float32)
    ref = np.stack([map_coordinates(coarse[..., j], coords, order=1, mode="nearest") for j in range(4)], axis=1)
    got = upsample_bilinear(coarse, h, w, k)
    assert got.dtype == np.float32 and got.shape == (h, w, 4)
    assert got.reshape(-1, 4).tobytes() == ref.tobytes()
