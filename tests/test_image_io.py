"""Image files: EXR (OpenImageIO), PNG 8/16 (OpenCV), Middlebury .flo -- round trips, layout, determinism."""
from __future__ import annotations

import os
import struct

import numpy as np
import pytest

from room_pipeline.errors import InputError
from room_pipeline.io.images import (read_exr, read_flo, read_png, write_exr, write_flo, write_png8,
                                     write_png16)

RNG = np.random.default_rng(0)


def _no_temp_files(folder):
    assert not [p for p in os.listdir(folder) if ".tmp" in p]


@pytest.mark.parametrize("shape,channels", [((17, 23), None), ((17, 23, 3), ("nx", "ny", "nz")),
                                            ((5, 4, 2), ("u", "v")), ((6, 7, 4), None)])
def test_exr_round_trip_bit_exact(tmp_path, shape, channels):
    a = RNG.normal(0, 1e-2, shape).astype(np.float32)
    a.flat[0] = 0.0
    a.flat[1] = 1e-30
    attrs = {"near_m": 1e-4, "frame": 12, "units": "m", "K": [[300.5, 0, 59.5], [0, 300.5, 59.5], [0, 0, 1]],
             "range": [0.5, 2.25], "meta": {"a": [1, 2], "b": "x"}, "flag": True, "ev": -0.677}
    write_exr(tmp_path / "a.exr", a, channels, attrs)
    b, names, got = read_exr(tmp_path / "a.exr")
    assert b.dtype == np.float32 and b.shape == a.shape and np.array_equal(a, b)
    if channels is not None:
        assert names == channels
    assert got == {"near_m": 1e-4, "frame": 12, "units": "m", "K": attrs["K"], "range": [0.5, 2.25],
                   "meta": {"a": [1, 2], "b": "x"}, "flag": True, "ev": -0.677}
    # deterministic bytes (no time stamp), written atomically
    write_exr(tmp_path / "b.exr", a, channels, attrs)
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    _no_temp_files(tmp_path)


def test_exr_is_zip_compressed_and_readable_by_openimageio_and_opencv(tmp_path):
    import OpenImageIO as oiio

    depth = np.linspace(2e-3, 5e-2, 40 * 30, dtype=np.float32).reshape(30, 40)
    write_exr(tmp_path / "depth.exr", depth, ("Y",), {"units": "m"})
    rgb = RNG.random((30, 40, 3), dtype=np.float32)
    write_exr(tmp_path / "rgb.exr", rgb)
    inp = oiio.ImageInput.open(str(tmp_path / "depth.exr"))
    spec = inp.spec()
    assert spec.get_string_attribute("compression") == "zip"
    assert spec.format == oiio.FLOAT and spec.nchannels == 1
    assert np.array_equal(inp.read_image(oiio.FLOAT)[..., 0], depth)
    assert spec.get_string_attribute("room:units") == "m"
    assert spec.get_string_attribute("DateTime") == ""
    inp.close()
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    import cv2

    try:
        d = cv2.imread(str(tmp_path / "depth.exr"), cv2.IMREAD_UNCHANGED)
        c = cv2.imread(str(tmp_path / "rgb.exr"), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:                 # OpenCV built without OpenEXR
        pytest.skip(f"OpenCV cannot read EXR here: {exc}")
    if d is None:
        pytest.skip("OpenCV cannot read EXR here (OPENCV_IO_ENABLE_OPENEXR read at import)")
    assert np.array_equal(d, depth)
    assert np.array_equal(c[..., ::-1], rgb)           # OpenCV gives BGR


def test_exr_half(tmp_path):
    a = RNG.random((8, 9, 3)).astype(np.float32)
    write_exr(tmp_path / "h.exr", a, half=True)
    b, _, _ = read_exr(tmp_path / "h.exr")
    assert np.array_equal(b, a.astype(np.float16).astype(np.float32))


def test_exr_errors(tmp_path):
    with pytest.raises(ValueError):
        write_exr(tmp_path / "x.exr", np.zeros((2, 2, 3), np.float32), ("a", "b"))
    with pytest.raises(ValueError):
        write_exr(tmp_path / "x.exr", np.zeros(5, np.float32))
    with pytest.raises(InputError):
        read_exr(tmp_path / "missing.exr")


@pytest.mark.parametrize("shape", [(13, 11), (13, 11, 3), (13, 11, 4)])
def test_png_round_trips_and_opencv_openimageio_agree(tmp_path, shape):
    import cv2
    import OpenImageIO as oiio

    for bits, writer, dtype in ((8, write_png8, np.uint8), (16, write_png16, np.uint16)):
        a = RNG.integers(0, np.iinfo(dtype).max + 1, shape, dtype=dtype)
        a.flat[0], a.flat[1] = 0, np.iinfo(dtype).max
        p = tmp_path / f"a{bits}.png"
        writer(p, a)
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        b = read_png(p)
        assert b.dtype == dtype and np.array_equal(a, b)
        writer(tmp_path / f"b{bits}.png", a)
        assert p.read_bytes() == (tmp_path / f"b{bits}.png").read_bytes()
        # other readers see RGB(A) in the right order and the right depth
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if len(shape) == 3:
            raw = raw[..., [2, 1, 0, 3][:shape[2]]]
        assert raw.dtype == dtype and np.array_equal(raw, a)
        cfg = oiio.ImageSpec()
        cfg.attribute("oiio:UnassociatedAlpha", 1)        # OpenImageIO premultiplies alpha unless told
        inp = oiio.ImageInput.open(str(p), cfg)
        o = inp.read_image(oiio.UINT8 if bits == 8 else oiio.UINT16)
        inp.close()
        assert np.array_equal(o.reshape(a.shape), a)
    with pytest.raises(ValueError):
        write_png8(tmp_path / "c.png", np.zeros((2, 2), np.uint16))
    _no_temp_files(tmp_path)


def test_flo_matches_middlebury_layout(tmp_path):
    h, w = 5, 7
    f = RNG.normal(0, 3, (h, w, 2)).astype(np.float32)
    write_flo(tmp_path / "a.flo", f)
    data = (tmp_path / "a.flo").read_bytes()
    assert data[:4] == b"PIEH"
    assert struct.unpack("<f", data[:4])[0] == 202021.25
    assert struct.unpack("<ii", data[4:12]) == (w, h)
    assert len(data) == 12 + h * w * 2 * 4
    # row-major, u and v interleaved: pixel (row 2, col 3)
    off = 12 + (2 * w + 3) * 8
    assert struct.unpack("<ff", data[off:off + 8]) == (f[2, 3, 0], f[2, 3, 1])
    g = read_flo(tmp_path / "a.flo")
    assert g.dtype == np.float32 and np.array_equal(f, g)
    # independent reader (the reference Middlebury/Sintel Python code reads it so)
    with open(tmp_path / "a.flo", "rb") as fh:
        assert np.fromfile(fh, np.float32, count=1)[0] == 202021.25
        ww, hh = np.fromfile(fh, np.int32, count=2)
        ref = np.fromfile(fh, np.float32, count=2 * ww * hh).reshape(hh, ww, 2)
    assert np.array_equal(ref, f)
    (tmp_path / "bad.flo").write_bytes(b"XXXX" + data[4:])
    with pytest.raises(InputError):
        read_flo(tmp_path / "bad.flo")
    (tmp_path / "short.flo").write_bytes(data[:-4])
    with pytest.raises(InputError):
        read_flo(tmp_path / "short.flo")
    _no_temp_files(tmp_path)
