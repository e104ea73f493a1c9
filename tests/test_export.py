"""Exports (COLMAP, nerfstudio transforms.json, TUM) read back by the real readers where installed."""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from room_pipeline.dataset import SequenceReader
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.export import FORMATS, build_parser, export_sequence, main, run_args
from room_pipeline.export.colmap import camera_to_world, world_to_camera
from room_pipeline.export.nerfstudio import (PNG16_DEPTH_UNIT_M, opencv_to_opengl, opengl_to_opencv,
                                             read_transforms)
from room_pipeline.export.tum import read_tum
from room_pipeline.io.atomic import write_json
from room_pipeline.io.images import read_exr, read_png, write_exr
from tests.test_dataset import N_FRAMES, SIZE, add_noisy, render_sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    s = render_sequence(tmp_path_factory.mktemp("out"))
    add_noisy(s)
    return s


@pytest.fixture(scope="module")
def reader(seq) -> SequenceReader:
    return SequenceReader(seq, ["rgb", "depth"])


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert msg and "\n" not in msg
    return msg


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- COLMAP


def test_colmap_model_read_by_pycolmap(seq, reader, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    out = tmp_path / "colmap"
    summary = export_sequence(seq, out, "colmap", point_stride=8)
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_images() == N_FRAMES and rec.num_cameras() == 1
    cam = rec.cameras[1]
    K = reader.K
    assert cam.model == pycolmap.CameraModelId.PINHOLE and (cam.width, cam.height) == (SIZE, SIZE)
    # COLMAP's pixel centres sit at +0.5 of OpenCV's
    np.testing.assert_array_equal(cam.params, [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])
    worst = 0.0
    for iid, im in rec.images.items():
        i = iid - 1
        assert im.name == f"frame_{i:04d}.png"
        c2w = np.eye(4)
        c2w[:3, :4] = im.cam_from_world().inverse().matrix()
        worst = max(worst, float(np.abs(c2w - reader.poses[i]).max()))
        assert (out / "images" / im.name).read_bytes() == (seq / "rgb" / im.name).read_bytes()
    assert worst < 1e-9
    # sparse points: each observation re-projects onto its 2-D point, at the ground-truth depth
    assert rec.num_points3D() == summary["points3D"] > 0
    for iid, im in rec.images.items():
        f = reader.frame(iid - 1)
        pts = [p for p in im.points2D if p.has_point3D()]
        assert len(pts) > 0
        for p in pts[::7]:
            X = rec.points3D[p.point3D_id].xyz
            xc = im.cam_from_world() * X
            np.testing.assert_allclose(cam.img_from_cam(xc), p.xy, atol=1e-6)
            u, v = int(round(p.xy[0] - 0.5)), int(round(p.xy[1] - 0.5))
            assert xc[2] == pytest.approx(float(f["depth"][v, u]), rel=1e-9)
            assert tuple(rec.points3D[p.point3D_id].color) == tuple(f["rgb"][v, u])


def test_colmap_without_points_or_images(seq, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    out = tmp_path / "c"
    export_sequence(seq, out, "colmap", point_stride=0, images=None)
    assert not (out / "images").exists()
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert rec.num_points3D() == 0 and rec.num_images() == N_FRAMES


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
       st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3))
def test_pose_conversions_invert(q, c):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = c
    qv, t = world_to_camera(T)
    assert qv[0] >= 0 and abs(np.linalg.norm(qv) - 1) < 1e-12
    np.testing.assert_allclose(camera_to_world(qv, t), T, atol=1e-12)
    gl = opencv_to_opengl(T)
    np.testing.assert_array_equal(opengl_to_opencv(gl), T)
    np.testing.assert_array_equal(gl[:3, 0], T[:3, 0])
    np.testing.assert_array_equal(gl[:3, 1:3], -T[:3, 1:3])
    np.testing.assert_array_equal(gl[:3, 3], T[:3, 3])


# --------------------------------------------------------------------------- nerfstudio


def test_nerfstudio_transforms_round_trip(seq, reader, tmp_path):
    out = tmp_path / "ns"
    export_sequence(seq, out, "nerfstudio", point_stride=16)
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["camera_model"] == "PINHOLE" and (doc["w"], doc["h"]) == (SIZE, SIZE)
    assert doc["depth_unit_scale_factor"] == PNG16_DEPTH_UNIT_M
    back = read_transforms(out)
    np.testing.assert_array_equal(back["poses"], reader.poses)          # exact: only sign flips
    np.testing.assert_allclose(back["K"], reader.K, atol=1e-12)
    np.testing.assert_allclose(back["timestamps"], reader.timestamps)
    assert back["file_paths"] == [f"images/frame_{i:04d}.png" for i in range(N_FRAMES)]
    K = reader.K
    for i, fr in enumerate(doc["frames"]):
        f = reader.frame(i)
        assert (out / fr["file_path"]).read_bytes() == (seq / "rgb" / f"frame_{i:04d}.png").read_bytes()
        # nerfstudio's ray through pixel index (col j, row r): camera-frame direction
        # ((j + 0.5 - cx) / fx, -(r + 0.5 - cy) / fy, -1) in OpenGL axes, rotated by transform_matrix
        M = np.array(fr["transform_matrix"])
        j, r = 11, 40
        d_gl = M[:3, :3] @ np.array([(j + 0.5 - doc["cx"]) / doc["fl_x"], -(r + 0.5 - doc["cy"]) / doc["fl_y"], -1.0])
        d_cv = f["pose"][:3, :3] @ (np.linalg.inv(K) @ [j, r, 1.0])
        np.testing.assert_allclose(d_gl, d_cv, atol=1e-12)
        np.testing.assert_array_equal(M[:3, 3], f["pose"][:3, 3])
        # depth: 16-bit PNG, 1e-5 m units, 0 = no hit (what nerfstudio's cv2.IMREAD_ANYDEPTH loader reads)
        dep = read_png(out / fr["depth_file_path"])
        assert dep.dtype == np.uint16
        metres = dep * doc["depth_unit_scale_factor"]
        np.testing.assert_allclose(metres, f["depth"], atol=PNG16_DEPTH_UNIT_M / 2 + 1e-9)
        assert np.all((dep == 0) == (f["depth"] == 0))


def test_nerfstudio_npy_depth_and_point_cloud_read_by_open3d(seq, reader, tmp_path):
    out = tmp_path / "ns"
    export_sequence(seq, out, "nerfstudio", depth="npy", images="rgb_noisy", point_stride=8)
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["depth_unit_scale_factor"] == 1.0
    for i, fr in enumerate(doc["frames"]):
        np.testing.assert_array_equal(np.load(out / fr["depth_file_path"]), reader.frame(i)["depth"])
        assert (out / fr["file_path"]).read_bytes() == (seq / "rgb_noisy" / f"frame_{i:04d}.png").read_bytes()
    o3d = pytest.importorskip("open3d")
    pcd = o3d.io.read_point_cloud(str(out / doc["ply_file_path"]))           # nerfstudio's reader of ply_file_path
    pts = np.asarray(pcd.points)
    assert len(pts) > 100 and pcd.has_colors()
    np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), 5e-3, atol=2e-5)   # on the 5 mm tube


def test_nerfstudio_without_depth(seq, tmp_path):
    out = tmp_path / "ns"
    export_sequence(seq, out, "nerfstudio", depth=None, point_stride=0)
    back = read_transforms(out / "transforms.json")
    assert back["depth_file_paths"] is None
    assert not (out / "depth").exists() and not (out / "sparse_points.ply").exists()


# --------------------------------------------------------------------------- TUM


def test_tum_round_trip(seq, reader, tmp_path):
    out = tmp_path / "tum"
    export_sequence(seq, out, "tum")
    ts, poses = read_tum(out)
    np.testing.assert_allclose(ts, reader.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses, reader.poses, atol=2e-9)


def test_tum_read_by_evo(seq, reader, tmp_path):
    pytest.importorskip("evo")
    from evo.tools import file_interface

    out = tmp_path / "tum"
    export_sequence(seq, out, "tum")
    traj = file_interface.read_tum_trajectory_file(str(out / "groundtruth.txt"))
    assert traj.num_poses == N_FRAMES
    np.testing.assert_allclose(traj.timestamps, reader.timestamps, atol=1e-6)
    np.testing.assert_allclose(traj.positions_xyz, reader.poses[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(np.array(traj.poses_se3), reader.poses, atol=2e-9)


# --------------------------------------------------------------------------- all formats


@pytest.mark.parametrize("fmt", FORMATS)
def test_exports_are_byte_deterministic_and_atomic(seq, tmp_path, fmt):
    a, b = tmp_path / "a", tmp_path / "b"
    export_sequence(seq, a, fmt)
    export_sequence(seq, b, fmt)
    ta, tb = tree_bytes(a), tree_bytes(b)
    assert ta == tb and "room_export.json" in ta
    assert json.loads(ta["room_export.json"])["format"] == fmt
    # an existing export is kept unless overwrite; replacing it leaves no temporary folder behind
    with pytest.raises(InputError) as e:
        export_sequence(seq, a, fmt)
    assert "not empty" in one_line(e)
    (a / "stale.txt").write_text("old")
    export_sequence(seq, a, fmt, overwrite=True)
    assert tree_bytes(a) == tb
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_failed_export_leaves_target_untouched(seq, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(seq, bare, ignore=shutil.ignore_patterns("rgb_noisy"))
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("keep")
    with pytest.raises(InputError) as e:
        export_sequence(bare, out, "colmap", images="rgb_noisy", overwrite=True)
    assert "rgb_noisy" in one_line(e)
    assert tree_bytes(out) == {"keep.txt": b"keep"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bare", "out"]


def test_bad_input(seq, tmp_path):
    with pytest.raises(InputError) as e:
        export_sequence(tmp_path / "nothing", tmp_path / "o", "tum")
    assert "nothing" in one_line(e)
    with pytest.raises(ConfigError) as e:
        export_sequence(seq, tmp_path / "o", "obj")
    assert "obj" in one_line(e)
    with pytest.raises(ConfigError) as e:
        export_sequence(seq, tmp_path / "o", "tum", point_stride=4)
    assert "point_stride" in one_line(e)
    with pytest.raises(InputError) as e:
        export_sequence(seq, seq / "colmap", "colmap")                    # inside the sequence
    one_line(e)
    # no depth maps: COLMAP points and nerfstudio depth cannot be made
    nodepth = tmp_path / "nodepth"
    shutil.copytree(seq, nodepth, ignore=shutil.ignore_patterns("depth"))
    for fmt in ("colmap", "nerfstudio"):
        with pytest.raises(InputError) as e:
            export_sequence(nodepth, tmp_path / fmt, fmt)
        assert "depth" in one_line(e)
    export_sequence(nodepth, tmp_path / "c0", "colmap", point_stride=0)
    # an empty sequence
    empty = tmp_path / "empty"
    shutil.copytree(seq / "calibration", empty / "calibration")
    write_json(empty / "metadata" / "render.json", {"frames": []})
    with pytest.raises(InputError) as e:
        export_sequence(empty, tmp_path / "e", "tum")
    assert "no frames" in one_line(e)
    assert not (tmp_path / "e").exists()


def test_depth_beyond_png16_range_and_distortion(seq, tmp_path):
    far = tmp_path / "far"
    shutil.copytree(seq, far)
    d, _, attrs = read_exr(far / "depth" / "frame_0001.exr")
    d[0, 0] = 0.7                                                         # metres: beyond 65535 x 1e-5 m
    write_exr(far / "depth" / "frame_0001.exr", d, channels=("Y",), attributes=attrs)
    with pytest.raises(InputError) as e:
        export_sequence(far, tmp_path / "ns", "nerfstudio")
    assert "frame_0001.exr" in one_line(e) and "npy" in one_line(e)
    export_sequence(far, tmp_path / "ns", "nerfstudio", depth="npy")
    assert np.load(tmp_path / "ns" / "depth" / "frame_0001.npy")[0, 0] == np.float32(0.7)
    cam = json.loads((far / "calibration" / "camera_params.json").read_text())
    cam["distortion"] = [0.1, 0.0, 0.0, 0.0, 0.0]
    write_json(far / "calibration" / "camera_params.json", cam)
    for fmt in ("colmap", "nerfstudio"):
        with pytest.raises(InputError) as e:
            export_sequence(far, tmp_path / f"d{fmt}", fmt)
        assert "distortion" in one_line(e)


def test_command_line(seq, tmp_path, capsys):
    assert main(["--format", "tum", str(seq), str(tmp_path / "t")]) == 0
    assert "tum" in capsys.readouterr().out and (tmp_path / "t" / "groundtruth.txt").is_file()
    assert main(["--format", "nerfstudio", str(seq), str(tmp_path / "n"), "--depth", "none",
                 "--point-stride", "0", "--images", "rgb_noisy"]) == 0
    assert read_transforms(tmp_path / "n")["depth_file_paths"] is None
    capsys.readouterr()
    assert main(["--format", "tum", str(seq), str(tmp_path / "t")]) == 2        # exists, no --overwrite
    err = capsys.readouterr().err
    assert err.startswith("room: error: ") and err.count("\n") == 1
    assert main(["--format", "tum", str(seq), str(tmp_path / "t2"), "--depth", "npy"]) == 2
    # the same arguments as a sub-command of a parser like room's (the hook for `room export`)
    p = argparse.ArgumentParser(prog="room")
    sub = p.add_subparsers(dest="command", required=True)
    build_parser(sub.add_parser("export")).set_defaults(func=run_args)
    args, extra = p.parse_known_args(["export", "--format", "colmap", str(seq), str(tmp_path / "c"),
                                      "--point-stride", "0"])
    assert extra == [] and args.func(args) == 0
    assert (tmp_path / "c" / "sparse" / "0" / "images.txt").is_file()
