"""Plain-NumPy reader of a rendered ROOM sequence (no torch): one frame at a time, only what is asked for.

A *sequence folder* is what the ``render`` stage writes (``<output_dir>/<patient>/<sequence>/``, see
:mod:`room_pipeline.render.sequence`); it is recognised by its ``metadata/render.json``.  The reader
loads that file and ``calibration/camera_params.json`` when it is built, and the image files of a
frame only when :meth:`SequenceReader.frame` is called, and only the folders of the requested
modalities.

Conventions of :meth:`SequenceReader.frame` (those of :mod:`room_pipeline.conventions`)
    Frames: ``index`` i = 0 .. len-1, the render stage's frame number (file ``frame_{i:04d}``);
    ``source_index`` the index of the pose in the planned / simulated trajectory it came from.
    World frame RAS+ in metres; camera frame OpenCV (x right, y down, z forward); pixel
    ``(u, v) = (column, row)`` with the centre of the top-left pixel at ``(0, 0)``, so a camera
    point ``(x, y, z)`` lands at ``u = fx x / z + cx``, ``v = fy y / z + cy``.

    Always present:
        ``index`` int, ``name`` str (``frame_NNNN``), ``timestamp`` float (s),
        ``pose`` (4, 4) float64 camera-to-world (metres), ``K`` (3, 3) float64,
        ``intrinsics`` dict (width, height, fx, fy, cx, cy in pixels; distortion
        (k1, k2, p1, p2, k3), zero for the rendered pinhole images).
    Per modality (only those requested):
        ``rgb``            (H, W, 3) uint8 sRGB.
        ``rgb_noisy``      (H, W, 3) uint8, the ``noise`` stage's frames (``rgb_noisy/``).
        ``depth``          (H, W) float32 planar z in metres; **0 where the ray hit nothing**
                           (never NaN: the files' convention, safe in losses and batches).
        ``relative_depth`` (H, W) float32 normalised inverse depth in [0, 1] (1 = the frame's
                           nearest hit, 0 = its farthest) decoded from the 16-bit PNG
                           (``(r - 1) / 65534``), 0 where no hit; ``relative_depth_range``
                           (2,) float64 [d_min, d_max] metres of the frame, from which
                           ``1/d = 1/d_max + relative_depth (1/d_min - 1/d_max)``.
        ``normals``        (H, W, 3) float32 unit normals in the camera frame, facing the camera;
                           0 where no hit.
        ``flow``           (H, W, 2) float32 forward optical flow t -> t+1 in pixels (``[..., 0]``
                           along columns, ``[..., 1]`` along rows), from ``optical_flow/frame_NNNN.exr``
                           (half float, channels R, G) or ``.flo`` (Middlebury, float32), whichever
                           the render stage wrote, and ``flow_valid`` (H, W) bool
                           (visible in frame t+1, inside it, not occluded); the last frame has
                           zero flow and no valid pixel.
        ``segmentation``   (H, W) uint16 label = airway branch id + 1, 0 = no hit; the legend
                           (label -> branch id, generation, parent) is :attr:`SequenceReader.legend`.
        ``point_cloud``    (N, 3) float32 points in the **camera** frame (metres, row-major over the
                           hit pixels), ``point_cloud_normals`` (N, 3) float32 and, when the RGB was
                           rendered with it, ``point_cloud_colors`` (N, 3) uint8.  Read from
                           ``point_clouds/frame_NNNN.ply`` when the render stage wrote one, otherwise
                           built on demand from the stored depth (``z = depth``, ``x = (u - cx) / fx z``,
                           ``y = (v - cy) / fy z``), normals and RGB, with the stride of
                           ``point_clouds/point_clouds.json`` (``point_cloud_stride`` overrides it).
    ``valid`` (H, W) bool, the surface-hit mask, whenever a per-pixel geometric modality (depth,
    relative_depth, normals, segmentation) is requested (taken from the first of these that is).

Errors are :class:`~room_pipeline.errors.InputError` with one line naming the folder or file.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from ..errors import InputError
from ..io.images import read_exr, read_flo, read_png
from ..io.ply import read_ply
from ..io.storage import stride_mask
from .. import catalog
from ..catalog import FOLDERS, MODALITIES, RGB_NOISY  # noqa: F401 (FOLDERS, MODALITIES: re-exported)

#: the two JSON files that make a folder a rendered sequence (relative to it)
RENDER_JSON = Path(catalog.METADATA) / catalog.RENDER_JSON
CAMERA_JSON = Path(catalog.CALIBRATION) / catalog.CAMERA_JSON


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise InputError(f"not found: {path}")
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc.__class__.__name__})") from None


def is_sequence(path: str | os.PathLike) -> bool:
    """True when ``path`` is a rendered sequence folder (it holds ``metadata/render.json``)."""
    return catalog.SequencePaths(Path(path)).is_rendered()


def find_sequences(root: str | os.PathLike) -> list[Path]:
    """Rendered sequence folders under ``root``, sorted by path.

    ``root`` may be a sequence folder itself, a patient folder (``<output_dir>/<patient>``) or a
    dataset root (``<output_dir>``): the search looks at ``root``, its sub-folders and theirs
    (never deeper, so the thousands of frame files are not walked).  Raises InputError when
    ``root`` is not a folder; returns an empty list when it holds no sequence.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"dataset root not found (or not a folder): {root}")
    if is_sequence(root):
        return [root]
    found = []
    for child in sorted(p for p in root.iterdir() if p.is_dir()):
        if is_sequence(child):
            found.append(child)
            continue
        found.extend(sorted(g for g in child.iterdir() if g.is_dir() and is_sequence(g)))
    return sorted(found)


class SequenceReader:
    """Lazy reader of one rendered sequence folder (see the module docstring for the frame dict).

    ``modalities``: an iterable of names from :data:`MODALITIES`, or None for the default set: the
    per-pixel modalities the render stage recorded (``metadata/render.json`` "modalities"), plus
    ``rgb_noisy`` when its folder exists; never the point cloud (variable size: ask for it).
    Every requested modality's folder must exist (InputError naming it otherwise); files are
    read per frame, by :meth:`frame`.
    """

    def __init__(self, path: str | os.PathLike, modalities: Iterable[str] | None = None,
                 point_cloud_stride: int | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise InputError(f"sequence folder not found: {self.path}")
        if not (self.path / RENDER_JSON).is_file():
            raise InputError(f"{self.path}: not a rendered sequence (no {RENDER_JSON.as_posix()})")
        self.render_meta = _read_json(self.path / RENDER_JSON)
        frames = self.render_meta.get("frames") if isinstance(self.render_meta, dict) else None
        if not frames:
            raise InputError(f"{self.path / RENDER_JSON}: the sequence has no frames")
        try:
            self._index = np.array([int(f["index"]) for f in frames], dtype=np.int64)
            self._source = np.array([int(f.get("source_index", f["index"])) for f in frames], dtype=np.int64)
            self._timestamps = np.array([float(f["timestamp"]) for f in frames], dtype=np.float64)
            self._poses = np.array([f["pose"] for f in frames], dtype=np.float64)
            if self._poses.shape != (len(frames), 4, 4) or not np.all(np.isfinite(self._poses)):
                raise ValueError("pose")
            self._rel_range = [np.asarray(f.get("relative_depth_range_m", (0.0, 0.0)), dtype=np.float64)
                               for f in frames]
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{self.path / RENDER_JSON}: malformed 'frames' (index, timestamp, 4x4 pose)") from None
        cam = _read_json(self.path / CAMERA_JSON)
        try:
            self.intrinsics = {"width": int(cam["width"]), "height": int(cam["height"]),
                               "fx": float(cam["fx"]), "fy": float(cam["fy"]),
                               "cx": float(cam["cx"]), "cy": float(cam["cy"]),
                               "distortion": tuple(float(x) for x in cam.get("distortion", (0.0,) * 5))}
        except (KeyError, TypeError, ValueError):
            raise InputError(f"{self.path / CAMERA_JSON}: missing width/height/fx/fy/cx/cy") from None
        i = self.intrinsics
        self.K = np.array([[i["fx"], 0.0, i["cx"]], [0.0, i["fy"], i["cy"]], [0.0, 0.0, 1.0]])
        self._pc_doc: dict = {}
        self.modalities = self._resolve(modalities)
        self._legend: dict | None = None
        stride = point_cloud_stride if point_cloud_stride is not None else self._pc_doc.get("stride", 1)
        try:
            self.point_cloud_stride = int(stride)
            if self.point_cloud_stride < 1:
                raise ValueError
        except (TypeError, ValueError):
            raise InputError(f"point cloud stride must be an integer >= 1, got {stride!r}") from None

    # ------------------------------------------------------------------ set-up
    def _resolve(self, modalities: Iterable[str] | None) -> tuple[str, ...]:
        if modalities is None:
            rendered = set(self.render_meta.get("modalities") or [])
            mods = [m for m in MODALITIES if m in rendered and m != "point_cloud"]
            if (self.path / FOLDERS[RGB_NOISY]).is_dir():
                mods.append(RGB_NOISY)
        else:
            if isinstance(modalities, str):
                modalities = [modalities]
            mods = list(dict.fromkeys(modalities))
            unknown = [m for m in mods if m not in MODALITIES]
            if unknown:
                raise InputError(f"unknown modalities {unknown} (known: {', '.join(MODALITIES)})")
        for m in mods:
            folder = self.path / FOLDERS[m]
            if not folder.is_dir():
                raise InputError(f"modality '{m}' requested but {folder} does not exist")
        if "point_cloud" in mods:
            doc_path = catalog.SequencePaths(self.path).point_cloud_json
            self._pc_doc = _read_json(doc_path) if doc_path.is_file() else {"storage": "ply"}
            if self._pc_doc.get("storage") == "on_demand" and not (self.path / FOLDERS["depth"]).is_dir():
                raise InputError(f"{doc_path}: point clouds are built from depth, but {self.path / FOLDERS['depth']} "
                                 f"does not exist")
        return tuple(m for m in MODALITIES if m in mods)

    # ------------------------------------------------------------------ sequence-level
    def __len__(self) -> int:
        return len(self._index)

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def frame_ids(self) -> list[int]:
        """The frame numbers (``index`` in render.json; file ``frame_{id:04d}``)."""
        return self._index.tolist()

    @property
    def frame_names(self) -> list[str]:
        return [f"frame_{i:04d}" for i in self._index]

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) float64 seconds."""
        return self._timestamps.copy()

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 camera-to-world poses (metres, OpenCV camera, world RAS+)."""
        return self._poses.copy()

    @property
    def source_indices(self) -> np.ndarray:
        return self._source.copy()

    @property
    def legend(self) -> dict:
        """``segmentation/legend.json`` (label -> branch id, generation, parent); read on first use."""
        if self._legend is None:
            self._legend = _read_json(self.path / FOLDERS["segmentation"] / catalog.LEGEND_JSON)
        return self._legend

    def file(self, modality: str, i: int) -> Path:
        """Path of frame ``i``'s file of one modality (``flow``: the ``.exr`` or, when that is absent, ``.flo``)."""
        ext = {"depth": ".exr", "normals": ".exr", "flow": ".exr", "point_cloud": ".ply"}.get(modality, ".png")
        p = self.path / FOLDERS[modality] / catalog.frame_name(self._index[self._pos(i)], ext)
        if modality == "flow":
            # what render.json says was written; sequences from before render.storage: the .flo
            fmt = ((self.render_meta.get("storage") or {}).get("params") or {}).get("flow_format")
            if fmt == "flo" or (fmt is None and not p.is_file()):
                return p.with_suffix(".flo")
        return p

    def _pos(self, i: int) -> int:
        n = len(self._index)
        j = int(i)
        if j < 0:
            j += n
        if not 0 <= j < n:
            raise IndexError(f"frame {i} out of range for {n} frames of {self.path}")
        return j

    def __getitem__(self, i: int) -> dict[str, Any]:
        return self.frame(i)

    def __iter__(self) -> Iterator[dict[str, Any]]:
        for i in range(len(self)):
            yield self.frame(i)

    # ------------------------------------------------------------------ one frame
    def _check_shape(self, a: np.ndarray, path: Path, channels: int | None) -> np.ndarray:
        h, w = self.intrinsics["height"], self.intrinsics["width"]
        want = (h, w) if channels is None else (h, w, channels)
        if a.shape != want:
            raise InputError(f"{path}: shape {a.shape}, expected {want} from {CAMERA_JSON.as_posix()}")
        return a

    def _rgb(self, modality: str, i: int) -> np.ndarray:
        p = self.file(modality, i)
        a = read_png(p)
        if a.dtype != np.uint8:
            raise InputError(f"{p}: expected an 8-bit RGB PNG, got {a.dtype}")
        if a.ndim == 3 and a.shape[2] == 4:
            a = np.ascontiguousarray(a[..., :3])
        return self._check_shape(a, p, 3)

    def frame(self, i: int) -> dict[str, Any]:
        """The requested modalities of frame ``i`` (a position 0..len-1; negative counts from the end)."""
        j = self._pos(i)
        out: dict[str, Any] = {"index": int(self._index[j]), "name": f"frame_{int(self._index[j]):04d}",
                               "timestamp": float(self._timestamps[j]), "pose": self._poses[j].copy(),
                               "K": self.K.copy(), "intrinsics": dict(self.intrinsics)}
        mods = self.modalities
        valid = None
        for m in catalog.RGB_SOURCES:
            if m in mods:
                out[m] = self._rgb(m, j)
        if "depth" in mods:
            p = self.file("depth", j)
            d, _, _ = read_exr(p)
            d = self._check_shape(np.ascontiguousarray(d, dtype=np.float32), p, None)
            d = np.where(np.isfinite(d) & (d > 0), d, np.float32(0))
            out["depth"] = d
            valid = d > 0
        if "relative_depth" in mods:
            p = self.file("relative_depth", j)
            r = self._check_shape(read_png(p), p, None)
            if r.dtype != np.uint16:
                raise InputError(f"{p}: expected a 16-bit PNG, got {r.dtype}")
            hit = r > 0
            out["relative_depth"] = np.where(hit, (r.astype(np.float32) - 1) / np.float32(65534), np.float32(0))
            out["relative_depth_range"] = self._rel_range[j].copy()
            valid = hit if valid is None else valid
        if "normals" in mods:
            p = self.file("normals", j)
            n, _, _ = read_exr(p)
            n = self._check_shape(np.ascontiguousarray(n, dtype=np.float32), p, 3)
            out["normals"] = n
            valid = np.any(n != 0, axis=-1) if valid is None else valid
        if "flow" in mods:
            p = self.file("flow", j)
            if p.suffix == ".flo":
                fl = read_flo(p)
            else:
                fl = read_exr(p)[0]
                if fl.ndim != 3 or fl.shape[2] != 2:
                    raise InputError(f"{p}: expected a 2-channel (u, v) flow EXR, got shape {fl.shape}")
            out["flow"] = self._check_shape(np.ascontiguousarray(fl, dtype=np.float32), p, 2)
            pv = self.path / FOLDERS["flow"] / catalog.frame_name(self._index[j], ".png", prefix="valid")
            v = self._check_shape(read_png(pv), pv, None)
            out["flow_valid"] = v > 0
        if "segmentation" in mods:
            p = self.file("segmentation", j)
            s = self._check_shape(read_png(p), p, None)
            if s.dtype != np.uint16:
                raise InputError(f"{p}: expected a 16-bit label PNG, got {s.dtype}")
            out["segmentation"] = s
            valid = s > 0 if valid is None else valid
        if "point_cloud" in mods and self._pc_doc.get("storage") == "on_demand":
            out.update(self._point_cloud_on_demand(j, out))
        elif "point_cloud" in mods:
            p = self.file("point_cloud", j)
            vert, _ = read_ply(p)
            try:
                out["point_cloud"] = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float32)
                if "nx" in vert:
                    out["point_cloud_normals"] = np.stack([vert["nx"], vert["ny"], vert["nz"]], 1).astype(np.float32)
                if "red" in vert:
                    out["point_cloud_colors"] = np.stack([vert["red"], vert["green"], vert["blue"]], 1).astype(np.uint8)
            except KeyError:
                raise InputError(f"{p}: point cloud without x, y, z properties") from None
        if valid is not None:
            out["valid"] = valid
        return out

    def _point_cloud_on_demand(self, j: int, have: dict) -> dict:
        """The frame's point cloud from the stored depth (+ normals, rgb when their folders exist)."""
        if "depth" in have:
            d = have["depth"]
        else:
            p = self.file("depth", j)
            d = self._check_shape(np.ascontiguousarray(read_exr(p)[0], dtype=np.float32), p, None)
            d = np.where(np.isfinite(d) & (d > 0), d, np.float32(0))
        keep = stride_mask(d > 0, self.point_cloud_stride)
        vv, uu = np.nonzero(keep)                                        # row-major
        i = self.intrinsics
        z = d[vv, uu]
        # the renderer's arithmetic: float64 ray (z = 1) -> float32, times the float32 depth
        x = ((uu - i["cx"]) / i["fx"]).astype(np.float32) * z
        y = ((vv - i["cy"]) / i["fy"]).astype(np.float32) * z
        res = {"point_cloud": np.stack([x, y, z], axis=1).astype(np.float32)}
        if (self.path / FOLDERS["normals"]).is_dir():
            n = have.get("normals")
            if n is None:
                p = self.file("normals", j)
                n = self._check_shape(np.ascontiguousarray(read_exr(p)[0], dtype=np.float32), p, 3)
            res["point_cloud_normals"] = np.ascontiguousarray(n[vv, uu], dtype=np.float32)
        if (self.path / FOLDERS["rgb"]).is_dir() and self.file("rgb", j).is_file():
            rgb = have.get("rgb")
            if rgb is None:
                rgb = self._rgb("rgb", j)
            res["point_cloud_colors"] = np.ascontiguousarray(rgb[vv, uu])
        return res

    def __repr__(self) -> str:
        return f"SequenceReader({str(self.path)!r}, {len(self)} frames, modalities={list(self.modalities)})"
