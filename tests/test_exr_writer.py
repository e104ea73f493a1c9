"""room_pipeline.io.exr: the NumPy + ISA-L OpenEXR writer decodes, in OpenImageIO and OpenCV, to exactly
what OpenImageIO's own writer stores (every codec it encodes, half and float, special values)."""
from __future__ import annotations

import os

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
    for w in ("isal", "openimageio"):
        st = StorageParams.from_dict({"exr_writer": w})
        st.write_depth(tmp_path / f"d_{w}.exr", depth, hit)
        st.write_normals(tmp_path / f"n_{w}.exr", normals)
        st.write_flow(tmp_path / f"f_{w}.exr", flow)
        out[w] = [read_exr(tmp_path / f"{k}_{w}.exr") for k in "dnf"]
        assert ("ISA-L" if w == "isal" else "OpenImageIO") in st.precision()["exr_writer"]
    for (a, an, aa), (b, bn, ba) in zip(out["isal"], out["openimageio"]):
        assert np.array_equal(a, b) and an == bn and aa == ba
    with pytest.raises(ConfigError, match=r"render\.storage\.exr_writer"):
        StorageParams.from_dict({"exr_writer": "tiff"})
