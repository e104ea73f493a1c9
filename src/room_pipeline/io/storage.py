"""How each rendered modality is stored: precision, codec, point clouds, and the overlapped writer.

Config section ``render.storage`` (:class:`StorageParams`, documented in
``conf/render/default.yaml``).  Every choice below is measured by
``benchmarks/write_throughput.py`` (size, write time, read time, error against
the float32 render; ``benchmarks/results/write_throughput.md``).

Precision per modality (what :meth:`StorageParams.precision` writes into
``calibration/camera_params.json`` and ``metadata/render.json`` "storage")
    depth      float32 EXR (channel Y, metres) rounded to multiples of
               ``depth_quantum_m`` (default 2^-17 m: error <= 2^-18 m = 0.0038 mm
               at any depth), PXR24 compression (default ``depth_compression``):
               PXR24 keeps 16 significant bits of each float32 and a multiple
               k 2^-17 m with k < 2^16 has no more, so it is stored exactly below
               2^16 x 2^-17 m = 0.5 m (the default far plane; beyond, PXR24 adds
               <= 2^-16 x depth); less than half the bytes of ZIP at less
               encoding CPU (116 vs 248 kB, 10.9 vs 14.2 ms a frame:
               benchmarks/results/write_throughput.md).  ``depth_quantum_m: 0``
               keeps the cast's float32 (error 0 with a lossless codec, e.g. zip).
               ``depth_dtype: half`` stores half floats (relative error <= 2^-11:
               0.01 mm only up to 20 mm, so not the default).
    normals    half-float EXR (R, G, B = x, y, z of the unit normal): |error| <= 2^-12
               (2.4e-4) per component, since every component lies in [-1, 1].
    flow       half-float EXR (R, G = u, v pixels): |error| <= 2^-11 |flow| (0.016 px
               at 32 px), or ``flow_format: flo`` (Middlebury, float32, the paper's).
               Both PXR24-compressed: lossless on half floats (PXR24 only rounds
               32-bit floats); smaller than ZIP at about the same encoding CPU,
               read faster (benchmarks/results/write_throughput.md).
    writer     ``exr_writer: libdeflate`` (default): :mod:`room_pipeline.io.exr`, NumPy
               layout + libdeflate level 4 (the same bytes for the same frame; ISA-L,
               the codec until session 11, did not promise it): the same pixel values
               as OpenImageIO's writer, 9.8 CPU ms and 303 kB a file against 15.4 ms and
               311 kB for zlib at OpenEXR's level 4 (write_throughput_deflate.md, 24 real
               frames); ``openimageio``: OpenImageIO / OpenEXR.
    png        rgb, relative depth, segmentation, flow validity: lossless at every
               zlib ``png_level`` (default 1: about a third less CPU than 3 for
               11-18 % more bytes on rgb and relative depth); segmentation and flow
               validity with zlib's run-length strategy (half the bytes of the
               default strategy at the same CPU).

Point clouds (``point_clouds``)
    ``ply``: a compact binary PLY per frame of the valid (hit) pixels, every
    ``point_cloud_stride``-th row and column (float32 x, y, z; normals and colours
    as ``point_cloud_normals`` / colours when rendered).  ``on_demand``: no
    per-frame file; :class:`~room_pipeline.dataset.SequenceReader` builds the same
    cloud from the stored depth (``z = depth``, ``x = (u - cx) / fx z``), normals
    and RGB.  Either way ``point_clouds/point_clouds.json`` says which, so the
    folder is never empty.

Writer (:class:`FrameWriter`)
    ``write_threads`` encoder threads (OpenImageIO's EXR codecs, OpenCV's PNG
    encoder and file writes release the GIL) take the finished arrays of a frame
    while the next frame is cast; at most ``max_pending`` writes wait, so memory
    stays flat.  :meth:`FrameWriter.wait` returns when everything submitted is on
    disk (the first error is re-raised); the render stage calls it at the end of
    every block of frames, before the block's records go back to the driver.
"""
from __future__ import annotations

import collections
import concurrent.futures as cf
import dataclasses
from typing import Any, Callable, Mapping

import numpy as np

from ..catalog import POINT_CLOUD_JSON  # noqa: F401  (re-exported: the dataset reader's name for it)
from ..config.params import params_from_dict
from ..errors import ConfigError
from .images import EXR_COMPRESSIONS, write_exr, write_flo, write_png8, write_png16

#: 2^-17 m ~ 7.6 um: depth rounding step of the default (error <= half of it)
DEFAULT_DEPTH_QUANTUM_M = 2.0 ** -17
HALF_REL_ERROR = 2.0 ** -11           # round-to-nearest half float: relative error bound


@dataclasses.dataclass(frozen=True)
class StorageParams:
    """Keys of ``render.storage`` (see ``conf/render/default.yaml``)."""

    depth_dtype: str = "float32"
    depth_quantum_m: float = DEFAULT_DEPTH_QUANTUM_M
    depth_compression: str = "pxr24"
    normals_dtype: str = "half"
    normals_compression: str = "pxr24"
    flow_format: str = "exr"
    flow_dtype: str = "half"
    flow_compression: str = "pxr24"
    exr_writer: str = "libdeflate"
    png_level: int = 1
    point_clouds: str = "on_demand"
    point_cloud_stride: int = 1
    write_threads: int = 2
    max_pending: int = 16
    write_block: int = 8

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "StorageParams":
        if d is not None and not isinstance(d, Mapping):
            raise ConfigError(f"render.storage must be a mapping, got {d!r}")
        try:
            p = params_from_dict(cls, d, "render.storage")
        except ValueError as e:
            raise ConfigError(str(e).splitlines()[0]) from None
        for key in ("depth_dtype", "normals_dtype", "flow_dtype"):
            if getattr(p, key) not in ("float32", "half"):
                raise ConfigError(f"render.storage.{key} must be 'float32' or 'half', got {getattr(p, key)!r}")
        for key in ("depth_compression", "normals_compression", "flow_compression"):
            v = getattr(p, key)
            if not isinstance(v, str) or v.split(":")[0] not in EXR_COMPRESSIONS:
                raise ConfigError(f"render.storage.{key} must be one of {sorted(EXR_COMPRESSIONS)}, got {v!r}")
        if p.exr_writer not in ("libdeflate", "openimageio"):
            raise ConfigError(f"render.storage.exr_writer must be 'libdeflate' or 'openimageio', got {p.exr_writer!r}"
                              + (" ('isal' was replaced by 'libdeflate': deterministic bytes)"
                                 if p.exr_writer == "isal" else ""))
        if p.flow_format not in ("exr", "flo"):
            raise ConfigError(f"render.storage.flow_format must be 'exr' or 'flo', got {p.flow_format!r}")
        if p.point_clouds not in ("on_demand", "ply"):
            raise ConfigError(f"render.storage.point_clouds must be 'on_demand' or 'ply', got {p.point_clouds!r}")
        if not (isinstance(p.depth_quantum_m, (int, float)) and 0.0 <= p.depth_quantum_m <= 1e-3):
            raise ConfigError(f"render.storage.depth_quantum_m must be in [0, 1e-3] m, got {p.depth_quantum_m!r}")
        if not 0 <= int(p.png_level) <= 9:
            raise ConfigError(f"render.storage.png_level must be 0..9, got {p.png_level!r}")
        if p.point_cloud_stride < 1 or p.write_threads < 0 or p.max_pending < 1 or p.write_block < 1:
            raise ConfigError("render.storage: point_cloud_stride >= 1, write_threads >= 0, max_pending >= 1 "
                              "and write_block >= 1 required")
        return p

    # ------------------------------------------------------------------ encoding
    def depth_array(self, depth: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """The depth as stored (float32 metres, 0 = no hit): rounded to the quantum when one is set."""
        d = np.where(hit, depth, 0).astype(np.float32)
        q = float(self.depth_quantum_m)
        if q > 0 and self.depth_dtype == "float32":
            m, e = np.frexp(q)
            if m == 0.5 and float(d.max(initial=0.0)) < 2.0 ** 23 * q:
                # a power of two: scaling by it is exact in float32, so float32 rounding gives the float64 result
                d *= np.float32(1.0 / q)
                np.rint(d, out=d)
                d *= np.float32(q)
            else:
                d = (np.rint(d.astype(np.float64) / q) * q).astype(np.float32)
        return d

    def _pow2_quantum(self) -> bool:
        q = float(self.depth_quantum_m)
        return q > 0 and float(np.frexp(q)[0]) == 0.5

    # ------------------------------------------------------------------ files (run on the writer threads)
    def write_depth(self, path, depth: np.ndarray, hit: np.ndarray) -> None:
        """``depth/frame_NNNN.exr``: :meth:`depth_array` (a new array: ``depth`` is only read)."""
        write_exr(path, self.depth_array(depth, hit), channels=("Y",), half=self.depth_dtype == "half",
                  compression=self.depth_compression, writer=self.exr_writer,
                  attributes={"units": "m", "quantity": "planar z depth, 0 = no hit",
                              "quantum_m": float(self.depth_quantum_m) if self.depth_dtype == "float32" else 0.0})

    def write_normals(self, path, normals: np.ndarray) -> None:
        """``surface_normals/frame_NNNN.exr``: (H, W, 3) unit normals, camera frame."""
        write_exr(path, normals, half=self.normals_dtype == "half", compression=self.normals_compression,
                  writer=self.exr_writer, attributes={"frame": "OpenCV camera; R,G,B = x,y,z; unit; 0 = no hit"})

    def write_flow(self, path, flow: np.ndarray) -> None:
        """``optical_flow/frame_NNNN.exr`` (or ``.flo``): (H, W, 2) forward flow in pixels."""
        if self.flow_format == "flo":
            write_flo(path, flow)
            return
        write_exr(path, flow, channels=("R", "G"), half=self.flow_dtype == "half", compression=self.flow_compression,
                  writer=self.exr_writer, attributes={"units": "px", "quantity": "forward optical flow t -> t+1; R = u (columns), "
                                                         "G = v (rows)"})

    def write_flow_valid(self, path, valid: np.ndarray) -> None:
        """``optical_flow/valid_NNNN.png``: 8-bit, 255 = valid (zlib's run-length strategy: a mask)."""
        write_png8(path, np.asarray(valid, dtype=bool).view(np.uint8) * np.uint8(255), self.png_level, rle=True)

    def write_segmentation(self, path, labels: np.ndarray) -> None:
        """``segmentation/frame_NNNN.png``: 16-bit, label + 1 (0 = no hit), run-length strategy."""
        write_png16(path, (labels + 1).astype(np.uint16), self.png_level, rle=True)

    @property
    def flow_ext(self) -> str:
        return ".exr" if self.flow_format == "exr" else ".flo"

    def precision(self) -> dict:
        """Per-modality storage and its error bound (units stated), for the metadata."""
        q = float(self.depth_quantum_m)
        if self.depth_dtype == "half":
            depth_err = f"<= 2^-11 x depth (half float; 0.01 mm up to 20 mm)"
        elif q > 0:
            depth_err = f"<= {q / 2:.3g} m (rounded to multiples of {q:.6g} m) + float32 rounding (2^-24 relative)"
        else:
            depth_err = "float32 as cast (relative 2^-24)"
        flow = ({"file": "optical_flow/frame_NNNN.flo", "format": "Middlebury .flo, float32 (u, v) pixels",
                 "error": "float32 (relative 2^-24)"} if self.flow_format == "flo" else
                {"file": "optical_flow/frame_NNNN.exr",
                 "format": f"OpenEXR {self.flow_dtype}, channels R, G = u, v (pixels), "
                           f"{self.flow_compression} compression",
                 "error": ("<= 2^-11 x |flow| (half float, round to nearest)" if self.flow_dtype == "half"
                           else "float32 (relative 2^-24)")})
        flow["valid"] = "optical_flow/valid_NNNN.png, 8-bit, 255 = valid"
        out = {
            "depth": {"file": "depth/frame_NNNN.exr",
                      "format": f"OpenEXR {self.depth_dtype}, channel Y, metres, 0 = no hit, "
                                f"{self.depth_compression} compression",
                      "quantum_m": q if self.depth_dtype == "float32" else None, "error": depth_err},
            "normals": {"file": "surface_normals/frame_NNNN.exr",
                        "format": f"OpenEXR {self.normals_dtype}, channels R, G, B = x, y, z (unit, camera "
                                  f"frame), {self.normals_compression} compression",
                        "error": ("<= 2^-12 (2.44e-4) per component (half float)" if self.normals_dtype == "half"
                                  else "float32 (relative 2^-24)")},
            "flow": flow,
            "exr_writer": ("room_pipeline.io.exr: NumPy + libdeflate (level 4) for none/zip/zips/pxr24, "
                           "OpenImageIO otherwise; the same pixel values as OpenImageIO's writer"
                           if self.exr_writer == "libdeflate" else "OpenImageIO (OpenEXR library)"),
            "png": {"files": "rgb, relative_depth (16-bit), segmentation (16-bit), flow validity (8-bit)",
                    "zlib_level": int(self.png_level),
                    "zlib_strategy": "default; run-length (Z_RLE) for segmentation and flow validity",
                    "error": "lossless"},
            "point_clouds": self.point_cloud_doc(),
        }
        for mod, comp, dtype in (("depth", self.depth_compression, self.depth_dtype),
                                 ("normals", self.normals_compression, self.normals_dtype),
                                 ("flow", self.flow_compression, self.flow_dtype if self.flow_format == "exr" else "")):
            name = comp.split(":")[0]
            if mod == "flow" and self.flow_format == "flo" or EXR_COMPRESSIONS[name]:
                continue
            if name == "pxr24" and dtype == "float32" and mod == "depth" and self._pow2_quantum():
                # multiples k q of a power-of-two quantum with k < 2^16 have <= 16 significant bits: pxr24 keeps them
                out[mod]["error"] += (f"; pxr24 codec (16 significant bits) stores these exactly below "
                                      f"2^16 x quantum = {65536 * q:.6g} m, beyond adds <= 2^-16 x depth")
                out[mod]["exact_below_m"] = 65536 * q
            elif name == "pxr24" and dtype == "float32":   # float32 rounded to 24 bits (15 mantissa bits)
                out[mod]["error"] += "; pxr24 codec: plus <= 2^-16 relative"
            elif name == "pxr24":
                continue                                    # pxr24 keeps half floats exactly
            else:
                out[mod]["error"] += f"; lossy {name} codec: not bounded here (benchmarks/results/write_throughput.md)"
        return out

    def point_cloud_doc(self) -> dict:
        """Content of ``point_clouds/point_clouds.json``."""
        common = {"frame": "OpenCV camera (x right, y down, z forward), metres; z = planar depth",
                  "stride": int(self.point_cloud_stride),
                  "pixels": "valid (hit) pixels with row % stride == 0 and column % stride == 0, row-major"}
        if self.point_clouds == "ply":
            return {"storage": "ply", "files": "point_clouds/frame_NNNN.ply",
                    "format": "binary little-endian PLY: float x, y, z; float nx, ny, nz; uchar red, green, "
                              "blue when RGB was rendered", **common}
        return {"storage": "on_demand",
                "how": "no per-frame file: room_pipeline.dataset.SequenceReader(seq, ['point_cloud']) builds "
                       "each frame's cloud from depth/ (x = (u - cx) / fx * z, y = (v - cy) / fy * z), with "
                       "normals from surface_normals/ and colours from rgb/ when present",
                "error": "that of the stored depth", **common}


def stride_mask(hit: np.ndarray, stride: int) -> np.ndarray:
    """The hit pixels a point cloud of this stride keeps: rows and columns multiple of ``stride``."""
    if stride <= 1:
        return hit
    keep = np.zeros_like(hit)
    keep[::stride, ::stride] = hit[::stride, ::stride]
    return keep


class FrameWriter:
    """Encode and write files on ``threads`` background threads (0: at once, in the caller's thread)."""

    def __init__(self, threads: int = 2, max_pending: int = 16) -> None:
        self.threads = int(threads)
        self.max_pending = max(1, int(max_pending))
        self._pool = cf.ThreadPoolExecutor(self.threads, thread_name_prefix="room-write") if self.threads else None
        self._pending: collections.deque[cf.Future] = collections.deque()

    def submit(self, fn: Callable[..., Any], *args: Any, **kw: Any) -> None:
        if self._pool is None:
            fn(*args, **kw)
            return
        while len(self._pending) >= self.max_pending:
            self._pending.popleft().result()          # flat memory: wait for the oldest write
        self._pending.append(self._pool.submit(fn, *args, **kw))

    def wait(self) -> None:
        """Block until every submitted write is done; re-raise the first failure (after all have finished)."""
        error = None
        while self._pending:
            f = self._pending.popleft()
            try:
                f.result()
            except BaseException as exc:  # noqa: BLE001 - the first failure is re-raised once all are done
                error = error or exc
        if error is not None:
            raise error

    def close(self) -> None:
        try:
            self.wait()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None
