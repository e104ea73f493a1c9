"""Blender Cycles backend (render/blender.py): geometry of every pass against ray casting, determinism, robustness.

Tiny images and few samples keep the whole file well under a minute.  The
reference geometry is Open3D's RaycastingScene on the same triangles (open3d
and bpy share a process fine; pymeshlab must never be imported here: its
Embree breaks bpy's).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
o3d = pytest.importorskip("open3d")

from scipy import ndimage  # noqa: E402

from room_pipeline.errors import ConfigError  # noqa: E402
from room_pipeline.io.mesh import Mesh  # noqa: E402
from room_pipeline.render.blender import CyclesRenderer, CyclesSettings, linear_to_srgb8  # noqa: E402
from room_pipeline.render.camera import CameraIntrinsics  # noqa: E402
from room_pipeline.render.scene import Scene  # noqa: E402

FAST = CyclesSettings(samples=8, adaptive_threshold=0.0, denoise=False, max_bounces=1, threads=2)


# ----------------------------------------------------------------------------- helpers
def wavy_tube(radius=8e-3, length=0.12, n_theta=96, n_z=240) -> Mesh:
    """Closed tube along +z (capped), radius modulated so depth is not trivial; normals air -> tissue."""
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    z = np.linspace(0, length, n_z)
    T, Z = np.meshgrid(th, z)  # (n_z, n_theta)
    R = radius * (1 + 0.12 * np.sin(3 * T) * np.sin(Z / 7e-3) + 0.05 * np.cos(Z / 11e-3))
    v = np.stack([R * np.cos(T), R * np.sin(T), Z], -1).reshape(-1, 3)
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    # caps: fans around centre vertices
    c0, c1 = len(v), len(v) + 1
    v = np.concatenate([v, [[0, 0, 0], [0, 0, length]]])
    r0, r1 = idx[0], idx[-1]
    cap0 = np.stack([np.full(n_theta, c0), np.roll(r0, -1), r0], -1)
    cap1 = np.stack([np.full(n_theta, c1), r1, np.roll(r1, -1)], -1)
    mesh = Mesh(v, np.concatenate([faces, cap0, cap1]))
    assert mesh.signed_volume() > 0  # outward = from air into tissue
    return mesh


def look_pose(eye, target, up=(1.0, 0.0, 0.0)) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target`` (y down)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    P = np.eye(4)
    P[:3, :3] = np.stack([x, y, z], 1)
    P[:3, 3] = eye
    return P


def raycast(mesh: Mesh, cam: CameraIntrinsics, pose: np.ndarray):
    """Planar depth (inf = no hit) and camera-frame face normals from Open3D."""
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    d = cam.pixel_rays() @ pose[:3, :3].T
    nd = np.linalg.norm(d, axis=-1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(pose[:3, 3], d.shape), d / nd], -1).astype(np.float32)
    ans = rs.cast_rays(o3d.core.Tensor(rays))
    depth = ans["t_hit"].numpy() / nd[..., 0]
    normals = ans["primitive_normals"].numpy() @ pose[:3, :3]
    return depth, normals


def smooth_region(depth: np.ndarray, tol: float = 0.25) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood is all hit and varies by < ``tol`` relative: away from silhouette edges."""
    ok = np.isfinite(depth)
    d = np.where(ok, depth, 0.0)
    hi, lo = ndimage.maximum_filter(d, 3), ndimage.minimum_filter(np.where(ok, d, np.inf), 3)
    return ndimage.binary_erosion(ok, np.ones((3, 3))) & (hi / lo < 1 + tol)


def tube_poses(n=3, step=0.6e-3) -> np.ndarray:
    """Camera moving along the tube, slightly off-axis, turning a little every frame."""
    poses = []
    for i in range(n):
        eye = np.array([1.5e-3, -1.0e-3, 0.02 + i * step])
        yaw = math.radians(4.0 * i)
        tgt = eye + np.array([0.15 * math.sin(yaw) + 0.05, 0.1, 1.0])
        poses.append(look_pose(eye, tgt))
    return np.array(poses)


@pytest.fixture(scope="module")
def tube() -> Mesh:
    return wavy_tube()


# ----------------------------------------------------------------------------- settings
def test_settings_from_dict_rejects_unknown_key():
    s = CyclesSettings.from_dict({"samples": 32, "denoise": False, "seed": 3})
    assert (s.samples, s.denoise, s.seed) == (32, False, 3)
    with pytest.raises(ConfigError, match="sampels"):
        CyclesSettings.from_dict({"sampels": 32})
    with pytest.raises(ConfigError, match="denoise"):
        CyclesSettings.from_dict({"denoise": "yes"})
    with pytest.raises(ConfigError, match="samples"):
        CyclesSettings.from_dict({"samples": 0})
    assert CyclesSettings().texture == "per_point" and CyclesSettings.from_dict({"texture": "vertex"}).texture == "vertex"
    with pytest.raises(ConfigError, match="texture"):
        CyclesSettings.from_dict({"texture": "uv"})


def test_linear_to_srgb8():
    x = np.array([0.0, 0.0031308, 0.18, 1.0, 2.0, np.nan])
    np.testing.assert_array_equal(linear_to_srgb8(x), [0, 10, 118, 255, 255, 0])


# ----------------------------------------------------------------------------- geometry
def test_depth_normals_flow_match_raycast(tube):
    """Depth (planar z) within 0.5 % median, normals within a few degrees, flow within 0.1 px EPE."""
    cam = CameraIntrinsics(80, 64, 46.0, 46.0, 41.3, 30.2, near=1e-4, far=0.5)  # off-centre principal point
    poses = tube_poses(3)
    sc = Scene(tube, cam, poses, np.arange(3) * 0.1)
    with CyclesRenderer(sc, FAST) as r:
        out = r.render(1)
        last = r.render(2, ("flow",))
    assert last["flow"] is None and "last frame" in r.notes["flow"]

    zr, nr = raycast(tube, cam, poses[1])
    good = smooth_region(zr)
    assert good.sum() > 0.5 * cam.width * cam.height
    zc = out["depth"]
    rel = np.abs(zc - zr) / zr
    assert np.median(rel[good]) <= 0.005, np.median(rel[good])
    assert np.all(zc[~np.isfinite(zr)] == 0)

    # Cycles normals face the camera: opposite of the mesh's air -> tissue face normal (smooth shading: few degrees)
    cosang = np.sum(out["normals"] * -nr, -1)
    assert np.degrees(np.arccos(np.clip(np.median(cosang[good]), -1, 1))) < 3.0
    facing = np.sum(out["normals"] * cam.pixel_rays(), -1) < 0  # n . ray < 0: the normal faces the camera
    assert facing[good].mean() > 0.99

    # geometric forward flow t=1 -> t=2 from ray-cast depth and the relative pose
    X = cam.unproject(zr)
    P1, P2 = poses[1], poses[2]
    Xw = X @ P1[:3, :3].T + P1[:3, 3]
    X2 = (Xw - P2[:3, 3]) @ P2[:3, :3]
    uv2 = cam.project(X2.reshape(-1, 3)).reshape(cam.height, cam.width, 2)
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    fg = uv2 - np.stack([u, v], -1)
    assert np.median(np.linalg.norm(fg, axis=-1)[good]) > 0.5  # the test has real motion
    epe = np.linalg.norm(out["flow"] - fg, axis=-1)[good]
    print(f"depth median rel err {np.median(rel[good]):.2e}; normal median angle "
          f"{np.degrees(np.arccos(np.clip(np.median(cosang[good]), -1, 1))):.2f} deg; flow EPE mean {epe.mean():.4f} "
          f"p95 {np.percentile(epe, 95):.4f} px (median |flow| {np.median(np.linalg.norm(fg, axis=-1)[good]):.2f} px)")
    assert epe.mean() <= 0.1 and np.percentile(epe, 95) <= 0.1, (epe.mean(), np.percentile(epe, 95))


def test_intrinsics_known_point_projects_to_expected_pixel():
    """A fronto-parallel rectangle in front of a wall: Cycles' depth covers exactly the pixels K says.

    Cycles writes the Depth pass from one camera sample at the pixel centre (no
    filter average: verified here, the mask is binary), so a pixel is covered
    iff its OpenCV centre (integer u, v) projects inside the rectangle.  The
    rectangle's edges sit 0.3 px from pixel centres, so a half-pixel
    convention error or a wrong principal point / focal length flips a row or
    a column.  Off-centre principal point and fx != fy (Blender pixel aspect).
    """
    cam = CameraIntrinsics(72, 60, 52.0, 47.0, 30.6, 33.9, near=1e-4, far=1.0)
    pose = look_pose([0.01, 0.02, -0.03], [0.03, 0.01, 0.2], up=(0.3, 1.0, 0.1))
    z_fg, z_bg = 0.05, 0.1
    u0, u1, v0, v1 = 20.3, 43.7, 25.7, 36.3  # pixel bounds of the rectangle
    x0, x1 = (u0 - cam.cx) * z_fg / cam.fx, (u1 - cam.cx) * z_fg / cam.fx
    y0, y1 = (v0 - cam.cy) * z_fg / cam.fy, (v1 - cam.cy) * z_fg / cam.fy
    fg = np.array([[x0, y0, z_fg], [x1, y0, z_fg], [x1, y1, z_fg], [x0, y1, z_fg]])  # known 3-D points
    bg = np.array([[-0.3, -0.3, z_bg], [0.3, -0.3, z_bg], [0.3, 0.3, z_bg], [-0.3, 0.3, z_bg]])
    np.testing.assert_allclose(cam.project(fg), [[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]])  # normals away from the camera (into "tissue")
    vw = np.concatenate([fg, bg]) @ pose[:3, :3].T + pose[:3, 3]
    sc = Scene(Mesh(vw, faces), cam, pose[None], np.zeros(1))
    for seed in (0, 1):
        with CyclesRenderer(sc, CyclesSettings(**{**FAST.to_dict(), "samples": 16, "seed": seed})) as r:
            out = r.render(0, ("depth", "normals"))
        d = out["depth"]
        v, u = np.mgrid[0 : cam.height, 0 : cam.width]
        want = (u > u0) & (u < u1) & (v > v0) & (v < v1)
        np.testing.assert_array_equal(np.abs(d - z_fg) < 1e-5, want)
        np.testing.assert_allclose(d[~want], z_bg, rtol=1e-5)
        # unprojecting the depth gives back the known 3-D points (here: the rectangle's plane)
        np.testing.assert_allclose(cam.unproject(d)[want][:, 2], z_fg, rtol=1e-5)
        # planes facing the camera: normal (0, 0, -1) in the OpenCV camera frame
        np.testing.assert_allclose(out["normals"].reshape(-1, 3), np.tile([0, 0, -1.0], (d.size, 1)), atol=1e-4)


# ----------------------------------------------------------------------------- determinism, robustness
def test_same_seed_same_image_and_rebuild(tube):
    cam = CameraIntrinsics.from_fov(48, 48, 85.0)
    poses = tube_poses(2)
    sc = Scene(tube, cam, poses, np.arange(2) * 0.1)
    s = CyclesSettings(samples=4, adaptive_threshold=0.0, denoise=True, max_bounces=2, seed=7, threads=2)
    with CyclesRenderer(sc, s) as r:
        a = r.render(0, ("rgb",))["rgb"]
        r.render(1, ("rgb",))
        b = r.render(0, ("rgb",))["rgb"]
    with CyclesRenderer(sc, s) as r:
        c = r.render(0, ("rgb",))["rgb"]
    with CyclesRenderer(sc, CyclesSettings(**{**s.to_dict(), "seed": 8, "denoise": False})) as r:
        d = r.render(0, ("rgb",))["rgb"]
    with CyclesRenderer(sc, CyclesSettings(**{**s.to_dict(), "denoise": False})) as r:
        e = r.render(0, ("rgb",))["rgb"]
    assert a.dtype == np.float32 and a.shape == (48, 48, 3) and a.mean() > 0
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    assert not np.array_equal(d, e)  # the seed matters


def test_grazing_camera_outputs_finite(tube):
    """Camera 0.3 mm from the wall looking almost along it: no NaN/inf in any output."""
    cam = CameraIntrinsics.from_fov(48, 48, 85.0)
    z0 = 1e-3
    r_wall = 8e-3 * (1 + 0.05 * np.cos(z0 / 11e-3))  # wall radius at theta = 0 (the sin(3 theta) term vanishes)
    eye0 = np.array([r_wall - 0.2e-3, 0.0, z0])  # 0.2 mm from the wall
    poses = np.array([look_pose(eye0 + [0, 0, 1e-3 * i], eye0 + [0.4e-3, 0, 1e-3 * i + 0.05]) for i in range(2)])
    sc = Scene(tube, cam, poses, np.arange(2) * 0.1)
    with CyclesRenderer(sc, CyclesSettings(samples=4, denoise=True, threads=2)) as r:
        out = r.render(0)
    for k, a in out.items():
        assert a is not None and np.all(np.isfinite(a)), k
    assert (out["depth"] > 0).mean() > 0.9
    assert np.all(out["depth"] >= 0)
