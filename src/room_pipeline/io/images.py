"""Image files of the rendered modalities: float EXR, 8/16-bit PNG, Middlebury ``.flo``.

Every writer is atomic (:mod:`room_pipeline.io.atomic`) and deterministic: the
bytes depend only on the array and the attributes (no time stamps, no host
names), so a re-run reproduces the files bit for bit.

EXR (OpenImageIO)
    ``write_exr(path, array, channels, attributes)``: (H, W) or (H, W, C)
    float32 (``half=True`` for 16-bit half floats), scanline order, ZIP
    compression unless ``compression`` names another OpenEXR codec
    (:data:`EXR_COMPRESSIONS`; ``piz``, ``zip``, ``zips``, ``rle`` and ``none``
    are lossless, ``pxr24``, ``b44``, ``dwaa``, ``dwab`` lossy: the render stage
    chooses per modality from ``benchmarks/results/write_throughput.md``).  ``attributes`` become EXR header attributes: ``str``, ``int``,
    and ``float`` values exactly representable in float32 (and flat
    sequences of those) natively (EXR ``string`` / ``int`` / ``float`` /
    float array); anything else -- other floats (OpenImageIO's Python binding
    cannot write ``double`` attributes), dicts, nested lists -- as JSON text,
    the names of those listed in ``room:json_attributes``.  Names without a
    namespace are stored as ``room:<name>`` so they cannot collide with the
    standard attributes.  :func:`read_exr` returns the array, the channel
    names and exactly these attributes (prefix removed, JSON decoded, native
    float arrays as lists).  ``DateTime`` is suppressed: deterministic bytes.

PNG (OpenCV)
    ``write_png8`` / ``write_png16``: (H, W) grey, (H, W, 3) RGB or (H, W, 4)
    RGBA arrays (channel order **RGB**, converted to OpenCV's BGR on writing
    and back on reading), uint8 / uint16; zlib level ``level`` (0-9, default
    :data:`PNG_COMPRESSION`; lossless at every level, only size and time change;
    ``rle=True``: zlib's run-length strategy, for label images and masks).

Middlebury optical flow ``.flo``
    Little-endian: the float32 ``202021.25`` (the bytes ``PIEH``), int32
    width, int32 height, then ``height * width * 2`` float32 ``(u, v)``
    interleaved, row-major (row 0 first).  ``u`` is the horizontal (column)
    displacement in pixels, ``v`` the vertical (row) one.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import InputError
from . import exr
from .atomic import atomic_path, write_bytes

FLO_MAGIC = 202021.25
_FLO_TAG = b"PIEH"
ATTR_PREFIX = "room:"
JSON_LIST_ATTR = "room:json_attributes"
PNG_COMPRESSION = 3
#: OpenEXR codecs OpenImageIO writes (name -> lossless?)
EXR_COMPRESSIONS = {"none": True, "rle": True, "zips": True, "zip": True, "piz": True, "pxr24": False,
                    "b44": False, "b44a": False, "dwaa": False, "dwab": False}

_DEFAULT_CHANNELS = {1: ("Y",), 2: ("U", "V"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


# --------------------------------------------------------------------------- EXR


def _as_hwc(array: np.ndarray) -> np.ndarray:
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] < 1:
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {np.shape(array)}")
    return a


def _attr_name(name: str) -> str:
    return name if ":" in name else ATTR_PREFIX + name


def _set_attribute(spec, name: str, value: Any) -> bool:
    """Store one attribute natively when that is lossless; return True when it went in as JSON text."""
    import OpenImageIO as oiio

    key = _attr_name(name)
    if isinstance(value, str):
        spec.attribute(key, value)
        return False
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) \
            and -2**31 <= int(value) < 2**31:
        spec.attribute(key, int(value))
        return False
    arr = None
    if isinstance(value, (float, np.floating, list, tuple, np.ndarray)) and not isinstance(value, str):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
    if arr is not None and arr.ndim <= 1 and arr.size > 0 and np.all(np.isfinite(arr)) \
            and np.all(arr.astype(np.float32).astype(np.float64) == arr) \
            and (arr.ndim == 0) == isinstance(value, (float, np.floating)):
        if arr.ndim == 0:
            spec.attribute(key, float(arr))
        else:
            spec.attribute(key, oiio.TypeDesc(f"float[{arr.size}]"), tuple(float(v) for v in arr))
        return False
    from .atomic import _json_default
    spec.attribute(key, json.dumps(value, sort_keys=True, default=_json_default, allow_nan=False))
    return True


def _native_attributes(attributes: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The attributes as :mod:`room_pipeline.io.exr` stores them (names prefixed, JSON where
    :func:`_set_attribute` would use JSON), or None when one would be a native float array (OpenImageIO
    writes those)."""
    from .atomic import _json_default

    out: dict[str, Any] = {}
    as_json = []
    for k in sorted(attributes or {}):
        v = attributes[k]
        key = _attr_name(k)
        if exr.encodable_attribute(v):
            out[key] = v.item() if isinstance(v, np.generic) else v
            continue
        if isinstance(v, (list, tuple, np.ndarray)):
            try:
                arr = np.asarray(v, dtype=np.float64)
            except (TypeError, ValueError):
                arr = None
            if arr is not None and arr.ndim == 1 and arr.size > 0 and np.all(np.isfinite(arr)) \
                    and np.all(arr.astype(np.float32).astype(np.float64) == arr):
                return None                       # a native float array: OpenImageIO's writer
        out[key] = json.dumps(v, sort_keys=True, default=_json_default, allow_nan=False)
        as_json.append(key)
    if as_json:
        out[JSON_LIST_ATTR] = json.dumps(as_json)
    if any(len(k) > 31 for k in out):
        return None
    return out


def write_exr(path: str | os.PathLike, array: np.ndarray, channels: Sequence[str] | None = None,
              attributes: Mapping[str, Any] | None = None, half: bool = False,
              compression: str = "zip", writer: str = "libdeflate") -> None:
    """Write an (H, W) or (H, W, C) array as a float32 (or half) OpenEXR, atomically.

    ``channels`` defaults to Y / U,V / R,G,B / R,G,B,A by channel count.
    Arrays that are not float32 are converted (values must be finite or the
    caller accepts inf/NaN in the file).  ``compression``: a key of
    :data:`EXR_COMPRESSIONS` (``dwaa``/``dwab`` may carry a level,
    e.g. ``dwaa:45``).  ``writer``: ``libdeflate`` -- :mod:`room_pipeline.io.exr` (NumPy + libdeflate) for
    ``none``/``zip``/``zips``/``pxr24`` with attributes it stores natively, OpenImageIO otherwise;
    ``openimageio`` -- always OpenImageIO.  Both store the same pixel values.
    """
    import OpenImageIO as oiio

    if compression.split(":")[0] not in EXR_COMPRESSIONS:
        raise ValueError(f"EXR compression must be one of {sorted(EXR_COMPRESSIONS)}, got {compression!r}")
    a = _as_hwc(array)
    h, w, c = a.shape
    names = tuple(channels) if channels is not None else _DEFAULT_CHANNELS.get(c, tuple(f"C{i}" for i in range(c)))
    if len(names) != c:
        raise ValueError(f"{c} channels but {len(names)} channel names")
    native = _native_attributes(attributes) if writer == "libdeflate" else None
    if writer not in ("libdeflate", "openimageio"):
        raise ValueError(f"EXR writer must be 'libdeflate' or 'openimageio', got {writer!r}")
    if writer == "libdeflate" and compression in exr.CODECS and native is not None:
        exr.write_exr_scanline(path, a, names, half, compression, native)
        return
    pixel_type = oiio.HALF if half else oiio.FLOAT
    spec = oiio.ImageSpec(w, h, c, pixel_type)
    spec.channelnames = names
    spec.attribute("compression", compression)
    spec.attribute("openexr:lineOrder", "increasingY")
    # no DateTime (OpenImageIO adds the current time unless told otherwise): deterministic bytes
    spec.attribute("DateTime", "")
    as_json = [k for k in sorted(attributes or {}) if _set_attribute(spec, k, attributes[k])]
    if as_json:
        spec.attribute(JSON_LIST_ATTR, json.dumps(as_json))
    # half files get half buffers, converted here by NumPy (round to nearest even, as OpenEXR's own conversion:
    # the same bytes, and less CPU than OpenImageIO converting while it writes)
    with np.errstate(over="ignore"):            # beyond the half range: inf, as OpenEXR's conversion gives
        data = np.ascontiguousarray(a, dtype=np.float16 if half else np.float32)

    def writer(tmp: Path) -> None:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"OpenImageIO cannot create an EXR writer: {oiio.geterror()}")
        try:
            if not out.open(str(tmp), spec):
                raise OSError(f"cannot open {tmp} for writing: {out.geterror()}")
            if not out.write_image(data):
                raise OSError(f"cannot write {tmp}: {out.geterror()}")
        finally:
            out.close()

    with atomic_path(path, suffix=".exr") as tmp:
        writer(tmp)


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, tuple[str, ...], dict[str, Any]]:
    """(array float32 (H, W) for one channel else (H, W, C), channel names, our attributes)."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError(f"EXR not found: {path}")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read EXR: {oiio.geterror()}")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        if data is None:
            raise InputError(f"{path}: cannot read pixels: {inp.geterror()}")
        names = tuple(spec.channelnames)
        attrs: dict[str, Any] = {}
        as_json: list = []
        for p in spec.extra_attribs:
            if p.name == JSON_LIST_ATTR:
                as_json = json.loads(p.value)
            elif p.name.startswith(ATTR_PREFIX):
                v = p.value
                attrs[p.name[len(ATTR_PREFIX):]] = list(v) if isinstance(v, (list, tuple)) else v
        for k in as_json:
            key = k[len(ATTR_PREFIX):] if k.startswith(ATTR_PREFIX) else k
            if key in attrs:
                attrs[key] = json.loads(attrs[key])
    finally:
        inp.close()
    arr = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return (arr[..., 0] if spec.nchannels == 1 else arr), names, attrs


# --------------------------------------------------------------------------- PNG


def _png_bytes(image: np.ndarray, dtype, level: int = PNG_COMPRESSION, rle: bool = False) -> bytes:
    import cv2

    a = np.asarray(image)
    if a.dtype != dtype:
        raise ValueError(f"PNG writer expects {np.dtype(dtype).name}, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 3:
        if a.shape[2] == 3:
            a = a[..., ::-1]
        elif a.shape[2] == 4:
            a = a[..., [2, 1, 0, 3]]
        else:
            raise ValueError(f"PNG needs 1, 3 or 4 channels, got {a.shape[2]}")
    elif a.ndim != 2:
        raise ValueError(f"PNG image must be (H, W) or (H, W, C), got shape {a.shape}")
    flags = [cv2.IMWRITE_PNG_COMPRESSION, int(level)]
    if rle:
        flags += [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(a), flags)
    if not ok:
        raise OSError("OpenCV failed to encode PNG")
    return buf.tobytes()


def write_png8(path: str | os.PathLike, image: np.ndarray, level: int = PNG_COMPRESSION, rle: bool = False) -> None:
    """8-bit PNG (grey, RGB or RGBA uint8), atomically; ``level``: zlib level 0-9; ``rle``: zlib's run-length
    strategy (label images and masks: about half the bytes of the default strategy at the same speed)."""
    write_bytes(path, _png_bytes(image, np.uint8, level, rle))


def write_png16(path: str | os.PathLike, image: np.ndarray, level: int = PNG_COMPRESSION, rle: bool = False) -> None:
    """16-bit PNG (grey, RGB or RGBA uint16), atomically; ``level``: zlib level 0-9; ``rle`` as for 8 bits."""
    write_bytes(path, _png_bytes(image, np.uint16, level, rle))


def read_png(path: str | os.PathLike) -> np.ndarray:
    """A PNG as written: uint8 or uint16, (H, W) or (H, W, 3|4) in RGB(A) order."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"PNG not found: {path}")
    a = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
    if a is None:
        raise InputError(f"{path}: not a readable PNG")
    if a.ndim == 3 and a.shape[2] == 3:
        a = a[..., ::-1]
    elif a.ndim == 3 and a.shape[2] == 4:
        a = a[..., [2, 1, 0, 3]]
    return np.ascontiguousarray(a)


# --------------------------------------------------------------------------- Middlebury .flo


def encode_flo(flow: np.ndarray) -> bytes:
    f = np.asarray(flow)
    if f.ndim != 3 or f.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got shape {f.shape}")
    h, w = f.shape[:2]
    return (np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
            + np.ascontiguousarray(f, dtype="<f4").tobytes())


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> None:
    """Middlebury ``.flo`` of an (H, W, 2) flow (u, v) in pixels, atomically."""
    write_bytes(path, encode_flo(flow))


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 2) float32 flow of a Middlebury ``.flo`` file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"flow file not found: {path}")
    data = path.read_bytes()
    if len(data) < 12 or data[:4] != _FLO_TAG:
        raise InputError(f"{path}: not a Middlebury .flo file (bad magic)")
    w, h = (int(x) for x in np.frombuffer(data, "<i4", count=2, offset=4))
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise InputError(f"{path}: .flo size mismatch ({w}x{h}, {len(data)} bytes)")
    return np.frombuffer(data, "<f4", offset=12).reshape(h, w, 2).astype(np.float32)
