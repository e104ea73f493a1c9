"""room_pipeline.io.exr: the NumPy + libdeflate OpenEXR writer decodes, in OpenImageIO and OpenCV, to exactly
what OpenImageIO's own writer stores (every codec it encodes, half and float, special values), and writes the
same bytes for the same image in any process."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest

from room_pipeline.io import exr
from room_pipeline.io.images import read_exr, write_exr

SPECIAL = np.array([np.inf, -np.inf, np.nan, 3.4e38, -3.4e38, 3.4028235e38, 1e-40, -0.0, 0.0, 65504.0, 65520.0,
                    70000.0, 1.0 + 2.0 ** -23, 2.0 ** -17 * 12345], np.float32)


def _oiio_write(path, a, names, half, comp):
    import OpenImageIO as oiio

    a3 = a if a.ndim == 3 else a[..., None]
    spec = oiio.ImageSpec(a3.shape[1], a3.shape[0], a3.shape[2], oiio.HALF if half else oiio.FLOAT)
    spec.channelnames = tuple(names)
    spec.attribute("compression", comp)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    with np.errstate(over="ignore"):
        assert out.write_image(np.ascontiguousarray(a3, dtype=np.float16 if half else np.float32))
    out.close()


def _images():
    rng = np.random.default_rng(7)
    smooth = np.cumsum(rng.normal(0, 1e-3, (37, 53, 3)), axis=1).astype(np.float32)     # compressible
    noise = rng.normal(0, 100, (19, 23, 2)).astype(np.float32)                           # raw chunks
    special = np.resize(SPECIAL, (21, 17)).astype(np.float32)                            # 2 chunks, partial
    return [("smooth", smooth, ("R", "G", "B")), ("noise", noise, ("U", "V")), ("special", special, ("Y",)),
            ("one_row", smooth[:1, :5], ("B", "A", "Z"))]


@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("comp", sorted(exr.CODECS))
def test_decodes_exactly_as_openimageio_writes(tmp_path, comp, half):
    for name, a, names in _images():
        mine, ref = tmp_path / f"{name}_mine.exr", tmp_path / f"{name}_ref.exr"
        exr.write_exr_scanline(mine, a, names, half, comp, {"room:units": "m", "room:n": 3, "room:q": 0.5})
        _oiio_write(ref, a, names, half, comp)
        m, mn, attrs = read_exr(mine)
        r, rn, _ = read_exr(ref)
        assert mn == rn and m.shape == r.shape
        assert np.array_equal(m.view(np.uint32), r.view(np.uint32)), (name, comp, half)   # NaN payloads too
        assert attrs == {"units": "m", "n": 3, "q": 0.5}


def test_pxr24_float_matches_openexr_rounding(tmp_path):
    """PXR24 keeps 24 bits of a float32 (OpenEXR's floatToFloat24): relative error <= 2^-16, inf/NaN kept."""
    a = np.concatenate([SPECIAL, np.geomspace(1e-6, 1e6, 200).astype(np.float32)])[None, :]
    exr.write_exr_scanline(tmp_path / "p.exr", a, ("Y",), False, "pxr24")
    back, _, _ = read_exr(tmp_path / "p.exr")
    assert np.array_equal(back.view(np.uint32), (exr.float24_bits(a) << np.uint32(8)).view(np.uint32))
    fin = np.isfinite(a) & (np.abs(a) < 3e38) & (np.abs(a) > 1e-30)
    assert np.all(np.abs(back[fin] - a[fin]) <= 2.0 ** -16 * np.abs(a[fin]))
    assert np.isnan(back[0, 2]) and back[0, 0] == np.inf and back[0, 1] == -np.inf


def test_standard_readers_and_deterministic_bytes(tmp_path):
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    rgb = _images()[0][1]
    write_exr(tmp_path / "a.exr", rgb, half=True, compression="pxr24", attributes={"frame": "camera"})
    write_exr(tmp_path / "b.exr", rgb, half=True, compression="pxr24", attributes={"frame": "camera"})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    bgr = cv2.imread(str(tmp_path / "a.exr"), cv2.IMREAD_UNCHANGED)
    assert bgr is not None and np.array_equal(bgr[..., ::-1], rgb.astype(np.float16).astype(np.float32))
    d = np.abs(rgb[..., 0])
    write_exr(tmp_path / "d.exr", d, ("Y",), compression="pxr24")
    y = cv2.imread(str(tmp_path / "d.exr"), cv2.IMREAD_UNCHANGED)
    assert y is not None and np.array_equal(y, read_exr(tmp_path / "d.exr")[0])


def test_write_exr_routes_and_attributes(tmp_path):
    """Codecs of exr.CODECS without a level go to the NumPy writer; JSON attributes as with OpenImageIO;
    float-array attributes and other codecs (or a level) are written by OpenImageIO: same values back."""
    a = _images()[0][1]
    attrs = {"units": "m", "k": 2, "q": 0.25, "pose": [[1.0, 0.1], [0.0, 1.0]], "doc": {"a": 1}}
    write_exr(tmp_path / "n.exr", a, attributes=attrs, compression="zip")
    write_exr(tmp_path / "o.exr", a, attributes=attrs, compression="zip:4")     # OpenImageIO
    n, nn, na = read_exr(tmp_path / "n.exr")
    o, on, oa = read_exr(tmp_path / "o.exr")
    assert np.array_equal(n, o) and nn == on and na == oa == attrs
    write_exr(tmp_path / "f.exr", a, attributes={"v": [1.0, 2.0]}, compression="pxr24")   # float array: OIIO
    assert read_exr(tmp_path / "f.exr")[2] == {"v": [1.0, 2.0]}
    with pytest.raises(ValueError, match="compression"):
        exr.encode_exr(a, ("R", "G", "B"), True, "dwaa")
    with pytest.raises(ValueError, match="distinct"):
        exr.encode_exr(a, ("R", "R", "B"), True, "zip")


def test_storage_exr_writer_knob(tmp_path):
    """render.storage.exr_writer: both writers store the same depth, normals and flow values; stated in the metadata."""
    from room_pipeline.errors import ConfigError
    from room_pipeline.io.storage import StorageParams

    rng = np.random.default_rng(3)
    depth = rng.uniform(0.001, 0.3, (20, 30)).astype(np.float32)
    hit = depth > 0.01
    normals = rng.normal(size=(20, 30, 3)).astype(np.float32)
    flow = rng.normal(0, 5, (20, 30, 2)).astype(np.float32)
    out = {}
    for w in ("libdeflate", "openimageio"):
        st = StorageParams.from_dict({"exr_writer": w})
        st.write_depth(tmp_path / f"d_{w}.exr", depth, hit)
        st.write_normals(tmp_path / f"n_{w}.exr", normals)
        st.write_flow(tmp_path / f"f_{w}.exr", flow)
        out[w] = [read_exr(tmp_path / f"{k}_{w}.exr") for k in "dnf"]
        assert ("libdeflate" if w == "libdeflate" else "OpenImageIO") in st.precision()["exr_writer"]
    for (a, an, aa), (b, bn, ba) in zip(out["libdeflate"], out["openimageio"]):
        assert np.array_equal(a, b) and an == bn and aa == ba
    with pytest.raises(ConfigError, match=r"render\.storage\.exr_writer"):
        StorageParams.from_dict({"exr_writer": "tiff"})
    with pytest.raises(ConfigError, match="replaced by 'libdeflate'"):
        StorageParams.from_dict({"exr_writer": "isal"})


#: one process's encoding of :func:`_frame_like` in every codec the writer deflates: sha256 of the file bytes
_WRITE_IN_A_PROCESS = """
import hashlib, sys
import numpy as np
from room_pipeline.io import exr
y, x = np.mgrid[0:96, 0:128].astype(np.float32)
rng = np.random.default_rng(11)
n = np.stack([np.sin(x / 17.0), np.cos(y / 13.0), np.sin((x + y) / 29.0)], -1) + rng.normal(0, 1e-3, (96, 128, 3))
d = (0.02 + 0.01 * np.sin(x / 9.0) * np.cos(y / 7.0)).astype(np.float32)
for comp in ("zip", "zips", "pxr24"):
    for half in (True, False):
        print(comp, half, hashlib.sha256(exr.encode_exr(n, ("R", "G", "B"), half, comp)).hexdigest(),
              hashlib.sha256(exr.encode_exr(d, ("Y",), half, comp)).hexdigest())
"""


def _hashes_in_a_new_process() -> str:
    env = {**os.environ, "PYTHONHASHSEED": "random"}
    r = subprocess.run([sys.executable, "-c", _WRITE_IN_A_PROCESS], capture_output=True, text=True,
                       encoding="utf-8", env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_same_image_same_bytes_in_two_processes():
    """The product's promise (same config -> same bytes) holds for the EXR files: one image encoded in two
    separate processes gives one file, in every deflated codec, half and float (ISA-L, the codec before
    session 11, gave some chunk 1-2 bytes apart in two default runs; libdeflate is deterministic)."""
    first, second = _hashes_in_a_new_process(), _hashes_in_a_new_process()
    assert len(first.splitlines()) == 6 and first == second


def test_deflate_is_libdeflate_at_the_writers_level(tmp_path):
    """The chunks are libdeflate's zlib streams at DEFLATE_LEVEL (any zlib inflates them); a level outside
    libdeflate's 1..12 is refused."""
    import zlib

    import deflate

    data = np.arange(50000, dtype=np.uint16).tobytes()
    assert exr.deflate_zlib(data) == deflate.zlib_compress(data, exr.DEFLATE_LEVEL)
    assert zlib.decompress(exr.deflate_zlib(data)) == data
    a = _images()[0][1]
    for bad in (0, 13):
        with pytest.raises(ValueError, match="libdeflate level"):
            exr.encode_exr(a, ("R", "G", "B"), True, "zip", level=bad)
    custom = exr.encode_exr(a, ("R", "G", "B"), True, "zip", deflate=lambda b: zlib.compress(b, 6))
    (tmp_path / "z.exr").write_bytes(custom)
    assert np.array_equal(read_exr(tmp_path / "z.exr")[0], a.astype(np.float16).astype(np.float32))
    assert hashlib.sha256(custom).hexdigest() != hashlib.sha256(exr.encode_exr(a, ("R", "G", "B"), True, "zip")).hexdigest()
