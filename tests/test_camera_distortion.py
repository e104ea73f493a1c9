"""Brown-Conrady lens distortion (render/camera.py): the model against OpenCV, the undistortion's
convergence, and every rendered modality in the same distorted image (depth, flow, RGB)."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from room_pipeline.errors import ConfigError
from room_pipeline.render import flow as fm
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import RaycastRenderer
from tests.test_raycast import MM, look, scene, tilt, tube

#: SNRLab/TrackerlessBronchoscopicNavigation camera_data_ex_vivo_human.json (200x200 px, fx 127)
PUBLISHED = (-0.101, -0.152, 0.00096, -0.0049, 0.102)


def grid(cam: CameraIntrinsics) -> np.ndarray:
    u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
    return np.stack([u, v], axis=-1)


@pytest.mark.parametrize("cam", [
    CameraIntrinsics.from_fov(600, 600, 85.0, distortion=PUBLISHED),           # the render default's fx
    CameraIntrinsics(200, 200, 127.0, 127.0, 97.5, 101.6, distortion=PUBLISHED),   # the published calibration
    CameraIntrinsics.from_fov(64, 48, 120.0, distortion=(0.05, 0.01, -0.002, 0.003, 0.0)),   # pincushion, wide
])
def test_pixel_rays_project_back_onto_the_pixel_grid(cam):
    cam.check_distortion()
    rays = cam.pixel_rays()
    assert rays.shape == (cam.height, cam.width, 3) and np.all(rays[..., 2] == 1.0)
    uv = cam.project(rays.reshape(-1, 3)).reshape(cam.height, cam.width, 2)
    assert np.abs(uv - grid(cam)).max() < 1e-6            # Newton's round trip (measured ~2e-10 px at 600x600)
    # the forward model is OpenCV's
    ref, _ = cv2.projectPoints(rays.reshape(-1, 3), np.zeros(3), np.zeros(3), cam.K, np.array(cam.distortion))
    assert np.abs(ref.reshape(-1, 2) - uv.reshape(-1, 2)).max() < 1e-8
    # unproject(depth) projects back onto the pixel grid at any depth
    depth = np.linspace(1 * MM, 80 * MM, cam.width * cam.height).reshape(cam.height, cam.width)
    pts = cam.unproject(depth)
    assert np.allclose(pts[..., 2], depth)
    assert np.abs(cam.project(pts.reshape(-1, 3)).reshape(cam.height, cam.width, 2) - grid(cam)).max() < 1e-6


def test_opencv_fixed_point_undistortion_fails_at_the_corners_where_newton_converges():
    """Why Newton: cv2.undistortPoints' fixed-point iteration is off by > 0.05 (normalised: ~16 px) in the corners
    of the 600x600 default with the published coefficients; in the centre it agrees."""
    cam = CameraIntrinsics.from_fov(600, 600, 85.0, distortion=PUBLISHED)
    g = grid(cam)
    und = cv2.undistortPoints(g.reshape(-1, 1, 2), cam.K, np.array(cam.distortion)).reshape(cam.height, cam.width, 2)
    ours = cam.pixel_rays()[..., :2]
    err = np.linalg.norm(und - ours, axis=-1)
    assert err.max() > 0.05
    r = np.linalg.norm((g - [cam.cx, cam.cy]) / cam.fx, axis=-1)
    assert err[r < 0.4].max() < 1e-6


def test_zero_distortion_is_the_pinhole_exactly():
    cam = CameraIntrinsics.from_fov(40, 30, 85.0)
    assert not cam.has_distortion
    u, v = grid(cam)[..., 0], grid(cam)[..., 1]
    pin = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
    assert np.array_equal(cam.pixel_rays(), pin)


@pytest.mark.parametrize("coeffs", [(-0.5, 0.0, 0.0, 0.0, 0.0), (0.0, -0.3, 0.0, 0.0, 0.0),
                                    (float("nan"), 0.0, 0.0, 0.0, 0.0)])
def test_a_distortion_that_folds_the_image_is_refused(coeffs):
    cam = CameraIntrinsics.from_fov(600, 600, 85.0, distortion=coeffs)
    with pytest.raises(ValueError):
        cam.check_distortion()
    from room_pipeline.render.params import RenderParams

    with pytest.raises(ConfigError, match="render.distortion"):
        RenderParams.from_dict({"distortion": list(coeffs)})


def test_render_config_distortion_reaches_the_camera_and_cycles_refuses_it():
    from room_pipeline.render.params import RenderParams, camera_of

    p = RenderParams.from_dict({"distortion": list(PUBLISHED)})
    cam = camera_of(p)
    assert cam.distortion == PUBLISHED and cam.to_dict()["distortion"] == list(PUBLISHED)
    assert "distorted image" in cam.to_dict()["distortion_applied"]
    assert CameraIntrinsics.from_dict(cam.to_dict()) == cam
    with pytest.raises(ConfigError, match="Cycles"):
        RenderParams.from_dict({"distortion": list(PUBLISHED), "backend": "cycles"})
    with pytest.raises(ConfigError, match="5 numbers"):
        RenderParams.from_dict({"distortion": [0.1, 0.0]})


CAM_D = CameraIntrinsics.from_fov(96, 96, 85.0, distortion=PUBLISHED)


def test_distorted_depth_unprojects_onto_the_surface_and_projects_back():
    """Every hit pixel's point (depth * pixel_rays) lies on the tube wall and projects back onto its pixel."""
    radius = 5 * MM
    T = tilt(look([1 * MM, -0.5 * MM, 0.0], [0, 0, 1]), 6, -4)
    r = RaycastRenderer(scene(tube(radius=radius, n_theta=256, n_z=80), [T], camera=CAM_D))
    out = r.render(0, {"depth", "normals"})
    hit = out["hit"]
    assert hit.mean() > 0.5
    pts = CAM_D.unproject(out["depth"].astype(np.float64))
    world = pts[hit] @ T[:3, :3].T + T[:3, 3]
    rad = np.hypot(world[:, 0], world[:, 1])
    chord = radius * (1 - np.cos(np.pi / 256))              # the faceted tube lies between r cos(pi/n) and r
    assert np.all(rad > radius - chord - 2e-7) and np.all(rad < radius + 2e-7)
    uv = CAM_D.project(pts[hit])
    assert np.abs(uv - grid(CAM_D)[hit]).max() < 1e-4       # float32 depth


def test_distorted_flow_matches_opencv_projection_and_warps_exactly():
    """Flow of a known camera motion = cv2.projectPoints of the moved points minus the pixel; the next frame's
    exact cast at p + flow sees the same point."""
    T0 = tilt(look([0.5 * MM, 0.3 * MM, 0.0], [0, 0, 1]), 3, -2)
    T1 = tilt(look([0.2 * MM, 0.6 * MM, 1.5 * MM], [0, 0, 1]), 5, 1)
    r = RaycastRenderer(scene(tube(wobble=0.1), [T0, T1], camera=CAM_D))
    out = r.render(0, {"depth", "flow"})
    hit, valid = out["hit"], out["flow_valid"]
    assert valid.sum() > 0.3 * hit.size
    X = CAM_D.unproject(out["depth"].astype(np.float64))[valid]
    rel = fm.relative_pose(T0, T1)
    X1 = X @ rel[:3, :3].T + rel[:3, 3]
    ref, _ = cv2.projectPoints(X1, np.zeros(3), np.zeros(3), CAM_D.K, np.array(CAM_D.distortion))
    expect = ref.reshape(-1, 2) - grid(CAM_D)[valid]
    assert np.abs(out["flow"][valid] - expect).max() < 2e-3    # float32 flow / depth
    # the exact check: cast camera t+1 through p' and find the point at its depth
    uv1 = grid(CAM_D)[valid] + out["flow"][valid]
    d1, h1 = r.depth_at(T1, uv1)
    assert h1.all()
    assert np.abs(d1 - X1[:, 2]).max() < 1e-3 * X1[:, 2].max()


def test_distorted_render_is_the_pinhole_render_remapped():
    """Depth of the distorted camera = a finer, wider pinhole render resampled at the distorted pixels' rays
    (what any pinhole renderer + cv2.remap would give); agreement up to the bilinear resampling."""
    T = tilt(look([0.8 * MM, -0.4 * MM, 0.0], [0, 0, 1]), 5, 3)
    mesh = tube(wobble=0.12, n_theta=128, n_z=60)
    out_d = RaycastRenderer(scene(mesh, [T], camera=CAM_D)).render(0, {"depth"})
    rays = CAM_D.pixel_rays()
    half = int(np.ceil(np.abs(rays[..., :2]).max() * CAM_D.fx)) + 2
    wide = dataclasses.replace(CAM_D, width=2 * half * 2 + 1, height=2 * half * 2 + 1, fx=2 * CAM_D.fx,
                               fy=2 * CAM_D.fy, cx=2 * half, cy=2 * half, distortion=(0.0,) * 5)
    out_w = RaycastRenderer(scene(mesh, [T], camera=wide)).render(0, {"depth"})
    mx = (wide.fx * rays[..., 0] + wide.cx).astype(np.float32)
    my = (wide.fy * rays[..., 1] + wide.cy).astype(np.float32)
    dw = cv2.remap(out_w["depth"].astype(np.float32), mx, my, cv2.INTER_LINEAR)
    hw = cv2.remap(out_w["hit"].astype(np.float32), mx, my, cv2.INTER_LINEAR) == 1.0
    both = out_d["hit"] & hw
    assert both.mean() > 0.5
    rel = np.abs(dw[both] - out_d["depth"][both]) / out_d["depth"][both]
    assert np.median(rel) < 2e-3 and np.percentile(rel, 99) < 3e-2


def test_room_run_refuses_a_folding_distortion_with_one_line(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "room_pipeline.cli", "run", "--until", "phantom", f"output_dir={out}",
                        "render.distortion=[-0.5,0,0,0,0]"], cwd=root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("room: error: render.distortion") and "folds" in lines[0]
    assert not out.exists()
