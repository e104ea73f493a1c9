"""OpenEXR scanline files encoded with NumPy and libdeflate: the render stage's EXR writer.

Why not OpenImageIO for writing: on a 600x600 frame OpenImageIO 3.0 / OpenEXR 3.3 spend 8-17 ms of CPU
on an *uncompressed* file (its per-scanline pipeline), more than the deflate itself, and they hold
the GIL while casting is done on the same core.  Here a whole image is laid out by a few NumPy
operations and each chunk is deflated by libdeflate (the ``deflate`` package: standard zlib streams,
at two thirds of zlib's CPU for fewer bytes), so a frame's three EXR files cost about half the CPU of
OpenImageIO's writer (its figures: ``benchmarks/results/write_throughput.md``; the deflate codecs on
real frames: ``write_throughput_deflate.md``).

Why libdeflate: the product promises the same bytes for the same config, and the deflate stream is
part of the bytes.  ISA-L (the writer's codec until session 11) does not promise one stream for one
input (intel/isa-l issue #140: its output may change with the CPU's code path; two default runs
on this machine gave three normals files whose chunk deflated 1-2 bytes differently).  libdeflate's
compressor is deterministic for a given libdeflate version (its author, ebiggers/libdeflate issue
#400), and the version is the pinned ``deflate`` wheel's (constraints.txt), not the system's zlib.
``tests/test_exr_writer.py`` writes one image in two processes and compares the bytes.  Reading stays with OpenImageIO
(:func:`room_pipeline.io.images.read_exr`); the files are plain OpenEXR 2.0 single-part scanline files
that every OpenEXR reader opens.

Format written (OpenEXR file layout, "Technical Introduction" and "OpenEXR File Layout")
    magic 20000630, version 2, no flags; header attributes (sorted by name, as OpenEXR writes them):
    ``channels`` (chlist, channels sorted by name, HALF or FLOAT, sampling 1), ``compression``,
    ``dataWindow`` = ``displayWindow`` = (0, 0) - (W-1, H-1), ``lineOrder`` increasing Y,
    ``pixelAspectRatio`` 1, ``screenWindowCenter`` (0, 0), ``screenWindowWidth`` 1, then the caller's
    ``string`` / ``int`` / ``float`` attributes; the offset table (uint64 per chunk); the chunks
    (int32 first y, int32 byte count, data), each holding its scanlines channel by channel in the
    channel list's order, little-endian.  A chunk whose compressed form is not smaller than its raw
    data is stored raw, as OpenEXR does (readers tell by the byte count).

Codecs (the ones the render stage uses; others go to OpenImageIO)
    ``none``: 1 scanline a chunk, raw.
    ``zip`` (16 scanlines a chunk) / ``zips`` (1): the bytes split into even and odd halves, then
    the predictor ``d[i] = b[i] - b[i-1] + 128 (mod 256)``, then deflate (lossless).
    ``pxr24`` (16 scanlines): per scanline and channel, each HALF as its 16 bits and each FLOAT as its
    24-bit rounding (``floatToFloat24`` of OpenEXR's Pxr24 compressor: round to nearest on bit 7, no
    rounding into inf; NaN and inf kept), differenced along the line (mod 2^16 / 2^24), split into
    byte planes (most significant first), then deflate.  Lossless on HALF; FLOAT keeps 15 of 23
    mantissa bits (relative error <= 2^-16), exactly as OpenEXR's own encoder.
    ``level``: libdeflate level 1-12 (default :data:`DEFLATE_LEVEL`).
"""
from __future__ import annotations

import os
import struct
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .atomic import write_bytes

#: codecs encoded here: name -> (OpenEXR compression id, scanlines per chunk)
CODECS = {"none": (0, 1), "zips": (2, 1), "zip": (3, 16), "pxr24": (5, 16)}
#: libdeflate level (1-12).  On 24 real frames (benchmarks/results/write_throughput_deflate.md, CPU ms per file
#: encoded / kB): ISA-L 1 (the old codec) 4.5 / 350, libdeflate 1 8.0 / 329, libdeflate 4 9.8 / 303, libdeflate 6
#: 13.2 / 289, zlib 4 (OpenEXR's own level) 15.4 / 311: level 4 gives 13 % fewer bytes than the old codec for
#: ~16 CPU ms a frame (three files; about 1 % of a frame's render CPU)
DEFLATE_LEVEL = 4
#: libdeflate's levels
DEFLATE_LEVELS = range(1, 13)
_MAGIC = 20000630
_HALF, _FLOAT = 1, 2


def deflate_zlib(data: bytes, level: int = DEFLATE_LEVEL) -> bytes:
    """A zlib stream (RFC 1950) of ``data`` by libdeflate at ``level``: the same bytes for the same input."""
    import deflate

    return deflate.zlib_compress(data, level)


def _attr(name: str, type_name: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) + value


def encodable_attribute(value: Any) -> bool:
    """Whether :func:`write_exr_scanline` stores ``value`` natively (str, int32, float32-exact float)."""
    if isinstance(value, str):
        return True
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        return -2**31 <= int(value) < 2**31
    if isinstance(value, (float, np.floating)):
        return bool(np.isfinite(value)) and float(np.float32(value)) == float(value)
    return False


def _attribute_bytes(name: str, value: Any) -> bytes:
    if isinstance(value, str):
        return _attr(name, "string", value.encode())
    if isinstance(value, (int, np.integer)):
        return _attr(name, "int", struct.pack("<i", int(value)))
    return _attr(name, "float", struct.pack("<f", float(value)))


def float24_bits(a: np.ndarray) -> np.ndarray:
    """OpenEXR's ``floatToFloat24`` of float32 values, as uint32 (24 significant bits).

    Decoding is ``bits << 8`` read as a float32.
    """
    u = np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)
    s = u & np.uint32(0x80000000)
    e = u & np.uint32(0x7F800000)
    m = u & np.uint32(0x007FFFFF)
    i = ((e | m) + (m & np.uint32(0x80))) >> np.uint32(8)
    over = i >= np.uint32(0x7F8000)
    if over.any():                                  # would round into inf (or is inf / NaN): truncate
        trunc = (e | m) >> np.uint32(8)
        i = np.where(over, trunc, i)
        special = e == np.uint32(0x7F800000)
        if special.any():                           # inf: exponent only; NaN: mantissa >> 8, never 0
            mm = m >> np.uint32(8)
            nan = (e >> np.uint32(8)) | mm | (mm == 0).astype(np.uint32)
            i = np.where(special, np.where(m != 0, nan, e >> np.uint32(8)), i)
    return (s >> np.uint32(8)) | i


def _planes_pxr24(planar: np.ndarray, half: bool) -> np.ndarray:
    """(H, C, W) values -> (H, C, nbytes, W) uint8 byte planes of the differences along each line."""
    h, c, w = planar.shape
    if half:
        bits = planar.view(np.uint16)
        nb = 2
    else:
        bits = float24_bits(planar)
        nb = 3
    diff = np.empty_like(bits)
    diff[..., :1] = bits[..., :1]
    np.subtract(bits[..., 1:], bits[..., :-1], out=diff[..., 1:])     # wraps modulo 2^16 / 2^32
    out = np.empty((h, c, nb, w), dtype=np.uint8)
    for k in range(nb):
        shift = 8 * (nb - 1 - k)
        np.copyto(out[:, :, k], diff >> shift if shift else diff, casting="unsafe")
    return out


def _zip_prepare(raw: np.ndarray) -> bytes:
    """OpenEXR's ZIP predictor on one chunk's bytes: even bytes then odd bytes, then byte differences + 128."""
    b = raw.reshape(-1)
    t = np.concatenate([b[0::2], b[1::2]])
    d = np.empty_like(t)
    d[:1] = t[:1]
    np.subtract(t[1:], t[:-1], out=d[1:])
    d[1:] += np.uint8(128)
    return d.tobytes()


def encode_exr(array: np.ndarray, channels: Sequence[str], half: bool, compression: str = "pxr24",
               attributes: Mapping[str, Any] | None = None, level: int = DEFLATE_LEVEL,
               deflate: Callable[[bytes], bytes] | None = None) -> bytes:
    """The bytes of an OpenEXR file of an (H, W, C) array (channel k named ``channels[k]``).

    ``attributes``: name -> str / int / float (see :func:`encodable_attribute`), names as given.
    Values beyond the half range become inf when ``half`` (as NumPy's conversion and OpenEXR's do).
    ``deflate``: another zlib-stream encoder of a chunk (``level`` then unused), for
    ``benchmarks/write_throughput.py --deflate`` to compare codecs on the same chunks.
    """
    if compression not in CODECS:
        raise ValueError(f"compression must be one of {sorted(CODECS)}, got {compression!r}")
    if deflate is None and int(level) not in DEFLATE_LEVELS:
        raise ValueError(f"libdeflate level must be 1..12, got {level}")
    encode = deflate or (lambda b: deflate_zlib(b, int(level)))
    a = np.asarray(array)
    if a.ndim == 2:
        a = a[..., None]
    h, w, c = a.shape
    if len(channels) != c or len(set(channels)) != c:
        raise ValueError(f"{c} channels need {c} distinct names, got {tuple(channels)}")
    order = sorted(range(c), key=lambda k: channels[k])             # OpenEXR's channel list is sorted by name
    dtype = np.float16 if half else np.float32
    with np.errstate(over="ignore"):
        planar = np.empty((h, c, w), dtype=dtype)                   # scanline-major, channel by channel
        for j, k in enumerate(order):
            planar[:, j, :] = a[:, :, k]
    comp_id, lines = CODECS[compression]
    ptype = _HALF if half else _FLOAT
    chlist = b"".join(channels[k].encode() + b"\0" + struct.pack("<iB3xii", ptype, 0, 1, 1) for k in order) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    attrs = {"channels": _attr("channels", "chlist", chlist),
             "compression": _attr("compression", "compression", bytes([comp_id])),
             "dataWindow": _attr("dataWindow", "box2i", box),
             "displayWindow": _attr("displayWindow", "box2i", box),
             "lineOrder": _attr("lineOrder", "lineOrder", b"\0"),
             "pixelAspectRatio": _attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)),
             "screenWindowCenter": _attr("screenWindowCenter", "v2f", struct.pack("<ff", 0.0, 0.0)),
             "screenWindowWidth": _attr("screenWindowWidth", "float", struct.pack("<f", 1.0))}
    for name, value in (attributes or {}).items():
        if name in attrs:
            raise ValueError(f"attribute {name!r} is a standard OpenEXR attribute")
        if not encodable_attribute(value):
            raise ValueError(f"attribute {name!r}: {type(value).__name__} is not stored by this writer")
        if len(name) > 31:
            raise ValueError(f"attribute name {name!r} longer than 31 characters")
        attrs[name] = _attribute_bytes(name, value)
    header = struct.pack("<ii", _MAGIC, 2) + b"".join(attrs[k] for k in sorted(attrs)) + b"\0"
    raw_lines = planar.view(np.uint8).reshape(h, -1)                 # little-endian on every supported host
    packed = _planes_pxr24(planar, half).reshape(h, -1) if compression == "pxr24" else None
    chunks = []
    for y in range(0, h, lines):
        raw = raw_lines[y:y + lines]
        if compression == "none":
            data = raw.tobytes()
        else:
            src = packed[y:y + lines].tobytes() if packed is not None else _zip_prepare(raw)
            data = encode(src)
            if len(data) >= raw.size:                                # not smaller: stored raw, as OpenEXR does
                data = raw.tobytes()
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    offset = len(header) + 8 * len(chunks)
    table = np.empty(len(chunks), dtype="<u8")
    for k, ch in enumerate(chunks):
        table[k] = offset
        offset += len(ch)
    return header + table.tobytes() + b"".join(chunks)


def write_exr_scanline(path: str | os.PathLike, array: np.ndarray, channels: Sequence[str], half: bool,
                       compression: str = "pxr24", attributes: Mapping[str, Any] | None = None,
                       level: int = DEFLATE_LEVEL) -> None:
    """:func:`encode_exr` written atomically to ``path``."""
    write_bytes(path, encode_exr(array, channels, half, compression, attributes, level))
