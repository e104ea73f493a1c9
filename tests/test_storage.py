"""Storage per modality (render.storage): stated precision verified by reading every file back, standard readers,
point clouds on demand or as compact PLY, the .flo option, the threaded writer."""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from room_pipeline.dataset import SequenceReader
from room_pipeline.errors import ConfigError
from room_pipeline.io.images import read_exr, read_flo, write_exr
from room_pipeline.io.storage import FrameWriter, StorageParams, stride_mask
from tests.test_dataset import N_FRAMES, SIZE, render_sequence

#: the storage of the float32 reference: what the renderer computed, unrounded (ZIP: pxr24 rounds 32-bit floats)
EXACT = {"depth_quantum_m": 0.0, "normals_dtype": "float32", "flow_dtype": "float32", "point_clouds": "ply",
         "depth_compression": "zip", "normals_compression": "zip", "flow_compression": "zip"}
MODS = ("rgb", "depth", "relative_depth", "normals", "flow", "segmentation", "point_cloud")


@pytest.fixture(scope="module")
def seqs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("storage")
    return {"default": render_sequence(root / "default", modalities=MODS),
            "exact": render_sequence(root / "exact", modalities=MODS, storage=EXACT),
            "flo_ply": render_sequence(root / "flo", modalities=MODS,
                                       storage={"flow_format": "flo", "point_clouds": "ply", "point_cloud_stride": 2,
                                                "write_threads": 0})}


def test_stated_precision_holds_for_every_file_read_back(seqs):
    """Depth <= 2^-18 m (0.0038 mm), normals <= 2^-12 per component, flow <= 2^-11 |flow|, PNGs identical."""
    d, x = seqs["default"], seqs["exact"]
    cal = json.loads((d / "calibration" / "camera_params.json").read_text())
    st = cal["storage"]
    assert st["depth"]["quantum_m"] == 2.0 ** -17
    assert "2^-12" in st["normals"]["error"] and "2^-11" in st["flow"]["error"]
    worst = {"depth": 0.0, "normals": 0.0, "flow_rel": 0.0}
    for i in range(N_FRAMES):
        name = f"frame_{i:04d}"
        dd, _, attrs = read_exr(d / "depth" / f"{name}.exr")
        dx = read_exr(x / "depth" / f"{name}.exr")[0]
        assert attrs["units"] == "m" and attrs["quantum_m"] == 2.0 ** -17
        assert np.array_equal(dd > 0, dx > 0)
        worst["depth"] = max(worst["depth"], float(np.abs(dd.astype(np.float64) - dx).max()))
        q = np.rint(dd.astype(np.float64) / 2.0 ** -17)
        assert np.array_equal(q * 2.0 ** -17, dd.astype(np.float64))          # on the stated grid
        nd, nx = read_exr(d / "surface_normals" / f"{name}.exr")[0], read_exr(x / "surface_normals" / f"{name}.exr")[0]
        worst["normals"] = max(worst["normals"], float(np.abs(nd - nx).max()))
        fd, names, _ = read_exr(d / "optical_flow" / f"{name}.exr")
        fx = read_exr(x / "optical_flow" / f"{name}.exr")[0]
        assert names == ("R", "G") and fd.shape == (SIZE, SIZE, 2)
        err = np.abs(fd.astype(np.float64) - fx)
        assert np.all(err <= np.maximum(2.0 ** -11 * np.abs(fx), 2.0 ** -25))   # half: relative, subnormals absolute
        worst["flow_rel"] = max(worst["flow_rel"], float((err / np.maximum(np.abs(fx), 1e-30)).max()))
        for folder in ("rgb", "relative_depth", "segmentation"):                 # lossless
            assert (d / folder / f"{name}.png").read_bytes() == (x / folder / f"{name}.png").read_bytes()
    assert 0 < worst["depth"] <= 2.0 ** -18 * (1 + 1e-6)        # metres: <= 0.0038 mm, inside the 0.01 mm target
    assert 0 < worst["normals"] <= 2.0 ** -12
    assert worst["flow_rel"] <= 2.0 ** -11
    # smaller files: half normals and flow, rounded depth
    size = lambda s, f: sum(p.stat().st_size for p in (s / f).glob("frame_*"))  # noqa: E731
    for folder in ("depth", "surface_normals"):
        assert size(d, folder) < size(x, folder)


def test_depth_rounding_error_over_the_working_range(tmp_path):
    """0.1 mm .. 500 mm (near to far plane): stored depth within 2^-18 m; half floats would not be (> 20 mm)."""
    rng = np.random.default_rng(0)
    depth = np.exp(rng.uniform(np.log(1e-4), np.log(0.5), size=(64, 64))).astype(np.float32)
    depth[:3] = 0.0                                                   # no hit stays exactly 0
    st = StorageParams()
    write_exr(tmp_path / "d.exr", st.depth_array(depth, depth > 0), channels=("Y",), compression=st.depth_compression)
    back = read_exr(tmp_path / "d.exr")[0]
    assert np.all(back[:3] == 0)
    assert np.abs(back.astype(np.float64) - depth).max() <= 2.0 ** -18 * (1 + 1e-6)
    write_exr(tmp_path / "h.exr", depth, channels=("Y",), half=True)
    half = read_exr(tmp_path / "h.exr")[0].astype(np.float64)
    far = depth > 0.05
    assert np.abs(half - depth)[far].max() > 1e-5                    # why depth is not half by default


def test_pxr24_keeps_the_depth_grid_below_half_a_metre_and_half_floats_exactly(tmp_path):
    """Default depth codec PXR24 (16 significant bits): k 2^-17 m with k < 2^16 is stored exactly, beyond the
    stated 2^-16 x depth holds; on half-float normals and flow PXR24 is lossless."""
    rng = np.random.default_rng(1)
    st = StorageParams()
    assert st.depth_compression == "pxr24" and st.normals_compression == "pxr24" and st.flow_compression == "pxr24"
    doc = st.precision()["depth"]
    assert doc["exact_below_m"] == 0.5 and "2^-16" in doc["error"]
    near = np.exp(rng.uniform(np.log(1e-4), np.log(0.5), size=(48, 48))).astype(np.float32)
    near[0, :4] = [0.5, 0.5 - 2.0 ** -17, 2.0 ** -17, 0.0]              # the far plane, its neighbour, 1 quantum, no hit
    far = rng.uniform(0.5, 4.0, size=(48, 48)).astype(np.float32)       # beyond the default far plane
    for depth, exact in ((near, True), (far, False)):
        stored = st.depth_array(depth, depth > 0)
        st.write_depth(tmp_path / "d.exr", depth, depth > 0)
        back = read_exr(tmp_path / "d.exr")[0].astype(np.float64)
        if exact:
            assert np.array_equal(back, stored.astype(np.float64))
        else:
            assert np.all(np.abs(back - stored) <= 2.0 ** -16 * stored)
            assert np.all(np.abs(back - depth) <= 2.0 ** -18 * (1 + 1e-6) + 2.0 ** -16 * depth)
    n = rng.normal(size=(40, 40, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    flow = rng.normal(scale=30.0, size=(40, 40, 2)).astype(np.float32)
    st.write_normals(tmp_path / "n.exr", n)
    st.write_flow(tmp_path / "f.exr", flow)
    assert np.array_equal(read_exr(tmp_path / "n.exr")[0], n.astype(np.float16).astype(np.float32))
    assert np.array_equal(read_exr(tmp_path / "f.exr")[0], flow.astype(np.float16).astype(np.float32))


def test_files_open_in_their_standard_readers(seqs):
    """OpenImageIO and OpenCV (EXR: depth Y, normals RGB, flow RG), Open3D (PLY), the Middlebury .flo layout."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2
    import open3d as o3d
    import OpenImageIO as oiio

    d, f = seqs["default"], seqs["flo_ply"]
    for i in range(N_FRAMES):
        name = f"frame_{i:04d}"
        depth = oiio.ImageInput.open(str(d / "depth" / f"{name}.exr")).read_image()[..., 0]
        assert np.array_equal(cv2.imread(str(d / "depth" / f"{name}.exr"), cv2.IMREAD_UNCHANGED), depth)
        n = oiio.ImageInput.open(str(d / "surface_normals" / f"{name}.exr")).read_image()
        assert np.array_equal(cv2.imread(str(d / "surface_normals" / f"{name}.exr"), cv2.IMREAD_UNCHANGED)[..., ::-1], n)
        flow = oiio.ImageInput.open(str(d / "optical_flow" / f"{name}.exr")).read_image()
        bgr = cv2.imread(str(d / "optical_flow" / f"{name}.exr"), cv2.IMREAD_UNCHANGED)   # (B = 0, G = v, R = u)
        assert flow.shape == (SIZE, SIZE, 2) and np.array_equal(bgr[..., 2], flow[..., 0])
        assert np.array_equal(bgr[..., 1], flow[..., 1]) and np.all(bgr[..., 0] == 0)
        raw = (f / "optical_flow" / f"{name}.flo").read_bytes()
        assert np.frombuffer(raw[:4], "<f4")[0] == np.float32(202021.25)
        w, h = np.frombuffer(raw[4:12], "<i4")
        flo = np.frombuffer(raw[12:], "<f4").reshape(h, w, 2)
        assert np.all(np.abs(flo - flow) <= np.maximum(2.0 ** -11 * np.abs(flo), 2.0 ** -25))
        pc = o3d.io.read_point_cloud(str(f / "point_clouds" / f"{name}.ply"))
        hit = depth > 0
        assert len(pc.points) == int(stride_mask(hit, 2).sum()) > 0 and pc.has_normals() and pc.has_colors()


def test_point_cloud_folder_is_never_empty_and_on_demand_equals_the_ply(seqs):
    d, x, f = seqs["default"], seqs["exact"], seqs["flo_ply"]
    doc = json.loads((d / "point_clouds" / "point_clouds.json").read_text())
    assert doc["storage"] == "on_demand" and doc["stride"] == 1 and not list((d / "point_clouds").glob("*.ply"))
    assert json.loads((f / "point_clouds" / "point_clouds.json").read_text())["storage"] == "ply"
    on_demand, ply = SequenceReader(d, ["point_cloud"]), SequenceReader(x, ["point_cloud"])
    for i in range(N_FRAMES):
        a, b = on_demand.frame(i), ply.frame(i)
        assert a["point_cloud"].shape == b["point_cloud"].shape and a["point_cloud"].dtype == np.float32
        # the same points up to the stored depth's rounding (2^-18 m along a ray of length <= 1.5)
        assert np.abs(a["point_cloud"] - b["point_cloud"]).max() <= 1.5 * 2.0 ** -18
        assert np.abs(a["point_cloud_normals"] - b["point_cloud_normals"]).max() <= 2.0 ** -12
        assert np.array_equal(a["point_cloud_colors"], b["point_cloud_colors"])
    # stride: on demand with stride 2 keeps the pixels the strided PLY keeps
    s2, p2 = SequenceReader(d, ["point_cloud"], point_cloud_stride=2).frame(1), SequenceReader(f, ["point_cloud"]).frame(1)
    assert s2["point_cloud"].shape == p2["point_cloud"].shape
    assert np.abs(s2["point_cloud"] - p2["point_cloud"]).max() <= 1.5 * 2.0 ** -18


def test_flo_option_reads_the_same_through_the_reader(seqs):
    a, b = SequenceReader(seqs["default"], ["flow"]), SequenceReader(seqs["flo_ply"], ["flow"])
    assert b.file("flow", 0).suffix == ".flo" and a.file("flow", 0).suffix == ".exr"
    for i in range(N_FRAMES):
        fa, fb = a.frame(i), b.frame(i)
        assert fa["flow"].dtype == np.float32 and np.array_equal(fa["flow_valid"], fb["flow_valid"])
        assert np.all(np.abs(fa["flow"] - fb["flow"]) <= np.maximum(2.0 ** -11 * np.abs(fb["flow"]), 2.0 ** -25))
        assert np.array_equal(read_flo(b.file("flow", i)), fb["flow"])


def test_render_json_states_the_storage_and_outputs_do_not_depend_on_writer_threads(seqs, tmp_path):
    meta = json.loads((seqs["default"] / "metadata" / "render.json").read_text())
    assert meta["storage"]["params"]["normals_dtype"] == "half"
    assert meta["storage"]["precision"]["flow"]["file"] == "optical_flow/frame_NNNN.exr"
    other = render_sequence(tmp_path, modalities=MODS, storage={"write_threads": 0, "write_block": 3})
    for p in seqs["default"].rglob("*"):
        if p.is_file() and p.suffix in (".exr", ".png", ".ply"):
            assert p.read_bytes() == (other / p.relative_to(seqs["default"])).read_bytes(), p


@pytest.mark.parametrize("bad", [{"flow_format": "png"}, {"normals_dtype": "float16"}, {"depth_compression": "lzma"},
                                 {"point_clouds": "always"}, {"depth_quantum_m": 0.01}, {"png_level": 10},
                                 {"write_block": 0}, {"unknown_key": 1}])
def test_bad_storage_config_is_one_config_error(bad):
    with pytest.raises(ConfigError) as e:
        StorageParams.from_dict(bad)
    assert "render.storage" in str(e.value) and "\n" not in str(e.value)


def test_frame_writer_overlaps_bounds_pending_and_reraises():
    w = FrameWriter(threads=2, max_pending=3)
    busy = threading.Semaphore(0)
    seen = []

    def job(k):
        time.sleep(0.01)
        seen.append(k)
        busy.release()

    for k in range(10):
        w.submit(job, k)
        assert len(w._pending) <= 3                      # flat memory: never more than max_pending waiting
    w.wait()
    assert sorted(seen) == list(range(10)) and not w._pending

    def boom():
        raise OSError("cannot write x.exr: disk full")

    w.submit(boom)
    w.submit(job, 99)
    with pytest.raises(OSError, match="disk full"):
        w.wait()
    assert 99 in seen                                    # the other writes finished before the error came back
    w.close()
    inline = FrameWriter(threads=0)
    inline.submit(seen.append, "now")
    assert seen[-1] == "now"


def test_ply_export_materialises_on_demand_point_clouds(seqs, tmp_path):
    """`room export -f ply`: one PLY per frame (Open3D reads it); world frame = camera points through the pose."""
    import open3d as o3d

    from room_pipeline.export import export_sequence, main

    d = seqs["default"]
    s = export_sequence(d, tmp_path / "cam", "ply", point_stride=2)
    assert s["frames"] == N_FRAMES and s["point_stride"] == 2
    export_sequence(d, tmp_path / "world", "ply", frame="world")
    r = SequenceReader(d, ["point_cloud"], point_cloud_stride=2)
    rw = SequenceReader(d, ["point_cloud"])
    for i in range(N_FRAMES):
        pc = o3d.io.read_point_cloud(str(tmp_path / "cam" / "points" / f"frame_{i:04d}.ply"))
        f = r.frame(i)
        assert np.array_equal(np.asarray(pc.points, dtype=np.float32), f["point_cloud"]) and pc.has_colors()
        w = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "world" / "points" / f"frame_{i:04d}.ply")).points)
        g = rw.frame(i)
        expect = g["point_cloud"].astype(np.float64) @ g["pose"][:3, :3].T + g["pose"][:3, 3]
        assert np.abs(w - expect).max() < 1e-7
    assert main(["-f", "ply", str(d), str(tmp_path / "bad"), "--frame", "world", "--point-stride", "0"]) == 2
    assert not (tmp_path / "bad").exists()
