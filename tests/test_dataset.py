"""Loaders: the NumPy SequenceReader and the torch RoomDataset on a sequence rendered by the real render stage."""
from __future__ import annotations

import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
from room_pipeline.dataset import MODALITIES, SequenceReader, find_sequences
from room_pipeline.errors import BackendUnavailable, InputError
from room_pipeline.io.atomic import write_json
from room_pipeline.io.images import read_png, write_png8
from room_pipeline.io.mesh import write_obj
from room_pipeline.paths import PatientPaths
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import decode_relative_depth16
from tests.test_raycast import look, tube

MM = 1e-3
N_FRAMES = 5
SIZE = 64
FOV = 85.0
RADIUS = 5 * MM
PATIENT, SEQUENCE = "patient_t", "sequence_000"
RENDERED = ["rgb", "depth", "relative_depth", "normals", "flow", "segmentation", "point_cloud"]


def tube_poses(n: int = N_FRAMES) -> np.ndarray:
    """Camera-to-world poses inside the tube: advancing 1.5 mm per frame, rolling 12 deg, tilting a little."""
    poses = []
    for k in range(n):
        a, b = np.radians(12.0 * k), np.radians(40.0 * k)
        eye = (0.6 * MM * np.cos(b), -0.4 * MM * np.sin(b), (2.0 + 1.5 * k) * MM)
        forward = (0.06 * np.sin(b + 0.3), 0.05 * np.cos(b), 1.0)
        poses.append(look(eye, forward, down=(-np.sin(a), np.cos(a), 0.0)))
    return np.array(poses)


def render_sequence(root: Path, n: int = N_FRAMES, size: int = SIZE, modalities=tuple(RENDERED),
                    storage: dict | None = None) -> Path:
    """Run the real ``render`` stage on a tube 'airway' (two branches, for two segmentation labels)."""
    from omegaconf import OmegaConf

    from room_pipeline.stages import render

    paths = PatientPaths(root, PATIENT)
    write_obj(paths.mesh, tube(radius=RADIUS))
    z0 = np.linspace(-5, 25, 7)[:, None] * MM
    z1 = np.linspace(25, 60, 8)[:, None] * MM
    graph = CentrelineGraph([
        GraphBranch(0, -1, 0, np.hstack([np.zeros((7, 2)), z0]), np.full(7, RADIUS)),
        GraphBranch(1, 0, 1, np.hstack([np.zeros((8, 2)), z1]), np.full(8, RADIUS))])
    write_json(paths.centreline_graph, graph.to_dict())
    poses = tube_poses(n)
    write_json(paths.sequence_metadata(SEQUENCE) / "trajectory.json",
               {"frames": [{"timestamp": 0.1 * k, "pose": poses[k].tolist()} for k in range(n)]})
    cfg = OmegaConf.create({"output_dir": str(root),
                            "render": {"width": size, "height": size, "fov_deg": FOV, "modalities": list(modalities),
                                       "poses": "planned", **({"storage": dict(storage)} if storage else {})}})
    render.run(cfg, f"{PATIENT}/{SEQUENCE}")
    return paths.sequence(SEQUENCE)


def add_noisy(seq: Path) -> None:
    """What the noise stage writes: ``rgb_noisy/frame_NNNN.png`` (here: seeded Gaussian noise)."""
    rng = np.random.default_rng(0)
    for p in sorted((seq / "rgb").glob("frame_*.png")):
        img = read_png(p).astype(np.int16) + rng.integers(-6, 7, size=(SIZE, SIZE, 3))
        write_png8(seq / "rgb_noisy" / p.name, np.clip(img, 0, 255).astype(np.uint8))


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    s = render_sequence(tmp_path_factory.mktemp("out"))
    add_noisy(s)
    return s


def one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert msg and "\n" not in msg
    return msg


# --------------------------------------------------------------------------- reader


def test_every_modality_shape_dtype_units(seq):
    r = SequenceReader(seq, MODALITIES)
    cam = CameraIntrinsics.from_fov(SIZE, SIZE, FOV)
    assert len(r) == N_FRAMES and r.frame_ids == list(range(N_FRAMES))
    assert r.frame_names[0] == "frame_0000"
    np.testing.assert_allclose(r.timestamps, 0.1 * np.arange(N_FRAMES))
    np.testing.assert_allclose(r.poses, tube_poses(), atol=1e-12)
    np.testing.assert_allclose(r.K, cam.K)
    for i in range(N_FRAMES):
        f = r.frame(i)
        assert f["index"] == i and f["name"] == f"frame_{i:04d}" and f["timestamp"] == pytest.approx(0.1 * i)
        assert f["pose"].shape == (4, 4) and f["pose"].dtype == np.float64
        assert f["K"].shape == (3, 3) and f["intrinsics"]["width"] == SIZE and f["intrinsics"]["fx"] == cam.fx
        for k in ("rgb", "rgb_noisy"):
            assert f[k].shape == (SIZE, SIZE, 3) and f[k].dtype == np.uint8
        assert not np.array_equal(f["rgb"], f["rgb_noisy"])
        valid, d = f["valid"], f["depth"]
        assert valid.dtype == bool and d.dtype == np.float32 and d.shape == (SIZE, SIZE)
        # the open far end of the tube is a hard case: pixels without a hit, depth exactly 0 there
        assert valid.mean() > 0.9 and (~valid).any()
        assert np.all(d[~valid] == 0) and np.all(np.isfinite(d))
        assert d[valid].min() > cam.near and d[valid].max() < 70 * MM          # metres, inside a 65 mm tube
        rel = f["relative_depth"]
        assert rel.dtype == np.float32 and rel.min() >= 0 and rel.max() == pytest.approx(1.0)
        assert np.all(rel[~valid] == 0)
        raw = np.where(valid, np.rint(rel * 65534) + 1, 0)
        np.testing.assert_allclose(decode_relative_depth16(raw, f["relative_depth_range"])[valid], d[valid], rtol=1e-3,
                                   atol=2.0 ** -18)          # stored depth: rounded to 2^-17 m (render.storage)
        n = f["normals"]
        assert n.dtype == np.float32 and n.shape == (SIZE, SIZE, 3)
        np.testing.assert_allclose(np.linalg.norm(n[valid], axis=1), 1.0, atol=3 ** 0.5 * 2.0 ** -12)   # half floats
        assert np.all(n[~valid] == 0)
        assert f["flow"].shape == (SIZE, SIZE, 2) and f["flow"].dtype == np.float32
        fv = f["flow_valid"]
        assert fv.dtype == bool and not np.any(fv & ~valid)
        if i == N_FRAMES - 1:
            assert not fv.any() and np.all(f["flow"] == 0)
        else:
            assert fv.mean() > 0.5
        s = f["segmentation"]
        assert s.dtype == np.uint16 and set(np.unique(s[valid])) <= {1, 2} and np.all(s[~valid] == 0)
        pc = f["point_cloud"]
        assert pc.dtype == np.float32 and pc.shape == (int(valid.sum()), 3)
        np.testing.assert_array_equal(pc[:, 2], d[valid])                   # row-major over hit pixels
        assert f["point_cloud_normals"].shape == pc.shape and f["point_cloud_colors"].dtype == np.uint8
    assert set(r.legend["labels"]) == {"1", "2"}
    labels = np.concatenate([r.frame(i)["segmentation"].ravel() for i in range(N_FRAMES)])
    assert {1, 2} <= set(np.unique(labels))


def test_depth_pose_intrinsics_put_points_on_the_tube(seq):
    """World points from depth, K and pose lie on the 5 mm tube; world normals point back to the axis."""
    r = SequenceReader(seq, ["depth", "normals"])
    for f in r:
        v = f["valid"]
        rays = np.linalg.inv(f["K"]) @ np.stack(np.meshgrid(np.arange(SIZE), np.arange(SIZE)) + [np.ones((SIZE, SIZE))],
                                                0).reshape(3, -1)
        cam = (rays * f["depth"].reshape(1, -1)).T[v.ravel()]
        world = cam @ f["pose"][:3, :3].T + f["pose"][:3, 3]
        rad = np.hypot(world[:, 0], world[:, 1])
        # a 48-gon: between r cos(pi/48) and r
        tol = 1e-7 + 1.5 * 2.0 ** -18      # depth stored rounded to 2^-17 m: a point moves <= 2^-18 m x |ray|
        assert rad.min() > RADIUS * np.cos(np.pi / 48) - tol and rad.max() < RADIUS + tol
        nw = f["normals"][v] @ f["pose"][:3, :3].T
        inward = -world[:, :2] / rad[:, None]
        assert np.mean(np.sum(nw[:, :2] * inward, axis=1)) > 0.95


def test_flow_matches_reprojection_with_pose_and_K(seq):
    """Back-project depth_t with K and pose_t, re-project into camera t+1: equals the stored flow (< 0.05 px)."""
    r = SequenceReader(seq, ["depth", "flow"])
    uu, vv = np.meshgrid(np.arange(SIZE, dtype=np.float64), np.arange(SIZE, dtype=np.float64))
    worst = 0.0
    for t in range(N_FRAMES - 1):
        f0, f1 = r.frame(t), r.frame(t + 1)
        K, d = f0["K"], f0["depth"].astype(np.float64)
        X = np.stack([(uu - K[0, 2]) / K[0, 0] * d, (vv - K[1, 2]) / K[1, 1] * d, d, np.ones_like(d)], -1)
        X1 = X @ (np.linalg.inv(f1["pose"]) @ f0["pose"]).T
        u1 = K[0, 0] * X1[..., 0] / X1[..., 2] + K[0, 2]
        v1 = K[1, 1] * X1[..., 1] / X1[..., 2] + K[1, 2]
        m = f0["flow_valid"]
        assert m.sum() > 100
        err = np.hypot(u1 - uu - f0["flow"][..., 0], v1 - vv - f0["flow"][..., 1])[m]
        worst = max(worst, float(err.max()))
    assert worst < 0.05


def test_default_modalities_and_lazy_reads(seq, monkeypatch):
    import room_pipeline.dataset.reader as rd

    r = SequenceReader(seq)
    # what render.json lists, plus the noise stage's frames; the point cloud only on request
    assert r.modalities == ("rgb", "rgb_noisy", "depth", "relative_depth", "normals", "flow", "segmentation")
    opened = []
    for name in ("read_png", "read_exr", "read_flo", "read_ply"):
        real = getattr(rd, name)
        monkeypatch.setattr(rd, name, lambda p, _real=real: (opened.append(Path(p).relative_to(seq).as_posix()),
                                                             _real(p))[1])
    r = SequenceReader(seq, ["depth"])
    assert opened == []                                       # building a reader reads no frame
    f = r.frame(3)
    assert opened == ["depth/frame_0003.exr"]
    assert set(f) == {"index", "name", "timestamp", "pose", "K", "intrinsics", "depth", "valid"}
    opened.clear()
    f = SequenceReader(seq, ["flow"]).frame(-1)               # negative positions count from the end
    assert opened == ["optical_flow/frame_0004.exr", "optical_flow/valid_0004.png"] and f["index"] == 4
    assert "valid" not in f
    f = SequenceReader(seq, []).frame(0)
    assert set(f) == {"index", "name", "timestamp", "pose", "K", "intrinsics"}
    with pytest.raises(IndexError):
        r.frame(N_FRAMES)


def test_find_sequences(seq, tmp_path):
    out = seq.parents[1]
    assert find_sequences(out) == [seq]
    assert find_sequences(seq.parent) == [seq]
    assert find_sequences(seq) == [seq]
    assert find_sequences(tmp_path) == []
    with pytest.raises(InputError) as e:
        find_sequences(tmp_path / "nope")
    assert "nope" in one_line(e)


def test_bad_input_one_line_errors(seq, tmp_path):
    with pytest.raises(InputError) as e:
        SequenceReader(tmp_path / "missing")
    assert "missing" in one_line(e)
    with pytest.raises(InputError) as e:
        SequenceReader(tmp_path)                              # a folder that is not a sequence
    assert "render.json" in one_line(e)
    with pytest.raises(InputError) as e:
        SequenceReader(seq, ["depth", "lidar"])
    assert "lidar" in one_line(e)
    part = tmp_path / "part"
    shutil.copytree(seq, part)
    shutil.rmtree(part / "surface_normals")
    with pytest.raises(InputError) as e:
        SequenceReader(part, ["rgb", "normals"])
    assert "surface_normals" in one_line(e)
    (part / "depth" / "frame_0002.exr").unlink()
    r = SequenceReader(part, ["depth"])
    r.frame(1)
    with pytest.raises(InputError) as e:
        r.frame(2)
    assert "frame_0002.exr" in one_line(e)
    meta = json.loads((part / "metadata" / "render.json").read_text())
    meta["frames"] = []
    write_json(part / "metadata" / "render.json", meta)
    with pytest.raises(InputError) as e:
        SequenceReader(part)
    assert "no frames" in one_line(e)


# --------------------------------------------------------------------------- torch


def test_torch_dataset_batches_equal_the_reader(seq):
    torch = pytest.importorskip("torch")
    from room_pipeline.dataset import RoomDataset

    mods = ["rgb", "rgb_noisy", "depth", "relative_depth", "normals", "flow", "segmentation"]
    ds = RoomDataset(seq.parents[1], mods)                  # found from the dataset root
    assert len(ds) == N_FRAMES
    r = SequenceReader(seq, mods)
    loader = torch.utils.data.DataLoader(ds, batch_size=2, shuffle=False, num_workers=0)
    seen = 0
    for batch in loader:
        b = len(batch["index"])
        assert batch["rgb"].shape == (b, 3, SIZE, SIZE) and batch["rgb"].dtype == torch.float32
        assert batch["depth"].shape == (b, 1, SIZE, SIZE) and batch["flow"].shape == (b, 2, SIZE, SIZE)
        assert batch["valid"].dtype == torch.bool and batch["segmentation"].dtype == torch.int64
        for k in range(b):
            f = r.frame(seen + k)
            assert batch["index"][k].item() == f["index"] and batch["name"][k] == f["name"]
            assert batch["sequence"][k] == str(seq)
            for key in ("rgb", "rgb_noisy"):
                np.testing.assert_array_equal(batch[key][k].numpy(), f[key].transpose(2, 0, 1) / np.float32(255))
            for key in ("normals", "flow"):
                np.testing.assert_array_equal(batch[key][k].numpy(), f[key].transpose(2, 0, 1))
            for key in ("depth", "relative_depth", "valid", "flow_valid", "segmentation"):
                np.testing.assert_array_equal(batch[key][k, 0].numpy(), f[key])
            for key in ("pose", "K", "relative_depth_range"):
                np.testing.assert_array_equal(batch[key][k].numpy(), f[key])
            assert batch["timestamp"][k].item() == f["timestamp"]
            np.testing.assert_array_equal(batch["intrinsics"][k].numpy(),
                                          [f["intrinsics"][x] for x in ("fx", "fy", "cx", "cy")])
        seen += b
    assert seen == N_FRAMES


def test_torch_pairs_transform_and_point_clouds(seq):
    torch = pytest.importorskip("torch")
    from room_pipeline.dataset import RoomDataset, room_collate

    calls = []

    def transform(item):
        calls.append(1)
        item["twice"] = item["T_t1_t"] * 2
        return item

    ds = RoomDataset([SequenceReader(seq)], ["depth", "flow", "point_cloud"], pairs=True, transform=transform)
    assert len(ds) == N_FRAMES - 1
    item = ds[1]
    f1, f2 = SequenceReader(seq, ["depth"]).frame(1), SequenceReader(seq, ["depth"]).frame(2)
    np.testing.assert_allclose(item["T_t1_t"].numpy(), np.linalg.inv(f2["pose"]) @ f1["pose"], atol=0)
    np.testing.assert_array_equal(item["t"]["depth"][0].numpy(), f1["depth"])
    np.testing.assert_array_equal(item["t1"]["depth"][0].numpy(), f2["depth"])
    assert calls and torch.equal(item["twice"], item["T_t1_t"] * 2)
    loader = torch.utils.data.DataLoader(ds, batch_size=3, collate_fn=room_collate)
    batch = next(iter(loader))
    assert isinstance(batch["t"]["point_cloud"], list) and len(batch["t"]["point_cloud"]) == 3
    assert batch["t"]["point_cloud"][0].shape[1] == 3 and batch["t"]["depth"].shape == (3, 1, SIZE, SIZE)
    assert batch["T_t1_t"].shape == (3, 4, 4)
    with pytest.raises(InputError):
        RoomDataset(seq.parents[2] / "empty_nothing_here")


def test_numpy_reader_never_imports_torch_and_missing_torch_is_one_clear_error(seq, monkeypatch):
    code = ("import sys; from room_pipeline.dataset import SequenceReader; "
            f"SequenceReader({str(seq)!r}).frame(0); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    monkeypatch.setitem(sys.modules, "torch", None)           # as if torch were not installed
    monkeypatch.delitem(sys.modules, "room_pipeline.dataset.torch_dataset", raising=False)
    with pytest.raises(BackendUnavailable) as e:
        importlib.import_module("room_pipeline.dataset.torch_dataset")
    assert "PyTorch" in one_line(e)
