"""nerfstudio / instant-ngp ``transforms.json`` of a rendered sequence with the ground-truth poses.

Layout written into the export folder::

    transforms.json              cameras and frames (below)
    images/frame_NNNN.png        copies of the rgb (or rgb_noisy) frames
    depth/frame_NNNN.png|.npy    ground-truth depth (optional, format below)
    sparse_points.ply            sparse world points from the depth maps (optional; nerfstudio's
                                 ``ply_file_path``, e.g. to initialise splatfacto)

Conventions
    nerfstudio and instant-ngp take the **OpenGL / Blender** camera frame (x right, y up, z
    backwards: the camera looks along -z) and a camera-to-world ``transform_matrix`` per frame.
    From the project's OpenCV camera-to-world pose ``P``: ``transform_matrix = P @ diag(1, -1, -1, 1)``
    (the camera's y and z axes flip; the world frame, RAS+ metres, is unchanged; the same matrix
    converts back).  Intrinsics ``fl_x, fl_y, cx, cy`` (pixels), ``w, h``, ``camera_model`` PINHOLE;
    both tools put the centre of the top-left pixel at (0.5, 0.5) (nerfstudio's rays go through
    pixel index + 0.5), the project (OpenCV) at (0, 0), so ``cx = cx_opencv + 0.5`` (same for cy).
    ``camera_angle_x`` / ``camera_angle_y`` (radians) are written for tools of the original NeRF
    format.  Frames are listed in time order (nerfstudio re-sorts by file name: the same order).
    The poses are metres in the CT's frame; nerfstudio recentres and rescales them itself
    (``auto_scale_poses``); instant-ngp users may need its ``scale`` / ``offset`` keys.

Depth (``depth_file_path`` per frame; planar z-depth, what nerfstudio's depth losses expect with
their default ``is_euclidean_depth=False``; 0 = no measurement)
    ``png16`` (default): 16-bit PNG in units of :data:`PNG16_DEPTH_UNIT_M` = 1e-5 m (10 um steps,
    at most 0.65535 m; a deeper hit is an error): train with
    ``--pipeline.datamanager.dataparser.depth-unit-scale-factor 1e-5`` (nerfstudio's default
    1e-3 means millimetres).  ``npy``: float32 metres, lossless: scale factor ``1.0``.  The
    factor is also written as ``depth_unit_scale_factor`` in transforms.json (a key nerfstudio
    ignores: it is a dataparser option).

``nerfstudio`` itself is not a dependency (``pip install nerfstudio`` pulls a CUDA build of torch);
:func:`read_transforms` is this module's own reader for round trips.
"""
from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..catalog import FOLDERS, RGB_SOURCES
from ..errors import ConfigError, InputError
from ..io.atomic import write_bytes, write_json
from ..io.images import write_png16
from ..io.ply import write_ply
from ..dataset.reader import SequenceReader
from .colmap import IMAGES_DIR, check_pinhole, copy_images, sample_depth_points

#: OpenCV camera axes (x right, y down, z forward) <-> OpenGL ones (x right, y up, z back)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
PIXEL_OFFSET = 0.5
PNG16_DEPTH_UNIT_M = 1e-5
DEPTH_FORMATS = ("png16", "npy")
DEPTH_DIR = Path("depth")
PLY_NAME = "sparse_points.ply"


def opencv_to_opengl(pose: np.ndarray) -> np.ndarray:
    """Camera-to-world pose(s) (..., 4, 4) with an OpenCV camera -> the same camera in OpenGL axes (and back)."""
    return np.asarray(pose, dtype=np.float64) @ CV_TO_GL


opengl_to_opencv = opencv_to_opengl


def _encode_depth(depth: np.ndarray, fmt: str, where: Path) -> bytes | np.ndarray:
    """``npy``: the .npy file bytes (float32 metres); ``png16``: the uint16 image in PNG16_DEPTH_UNIT_M units."""
    if fmt == "npy":
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
        return buf.getvalue()
    units = np.rint(depth.astype(np.float64) / PNG16_DEPTH_UNIT_M)
    if units.max(initial=0) > 65535:
        raise InputError(f"{where}: depth {float(depth.max()):.4f} m exceeds the 16-bit PNG range "
                         f"({65535 * PNG16_DEPTH_UNIT_M:g} m at {PNG16_DEPTH_UNIT_M:g} m per unit); "
                         "export with depth='npy'")
    return units.astype(np.uint16)


def write_nerfstudio(reader: SequenceReader, out_dir: Path, images: str = "rgb", depth: str | None = "png16",
                     point_stride: int = 16) -> dict[str, Any]:
    """Write ``transforms.json`` (+ images, depth, sparse points) of ``reader``'s sequence into ``out_dir``."""
    check_pinhole(reader)
    if images is None:
        raise ConfigError("the nerfstudio export needs images ('rgb' or 'rgb_noisy')")
    if depth is not None and depth not in DEPTH_FORMATS:
        raise ConfigError(f"depth must be one of {DEPTH_FORMATS} or None, got {depth!r}")
    if int(point_stride) < 0:
        raise ConfigError(f"point_stride must be >= 0 (0 = no point cloud), got {point_stride}")
    need_depth = depth is not None or int(point_stride) > 0
    if need_depth and not (reader.path / FOLDERS["depth"]).is_dir():
        raise InputError(f"{reader.path / FOLDERS['depth']} does not exist: export with depth=None and point_stride=0")
    out_dir = Path(out_dir)
    names = copy_images(reader, out_dir, images)
    ci = reader.intrinsics
    depth_reader = None
    if need_depth:
        has_rgb = (reader.path / FOLDERS["rgb"]).is_dir()
        depth_reader = SequenceReader(reader.path, ["depth", "rgb"] if has_rgb else ["depth"])
    frames = []
    cloud_xyz, cloud_rgb = [], []
    for i in range(len(reader)):
        rec: dict[str, Any] = {"file_path": (IMAGES_DIR / names[i]).as_posix(),
                               "transform_matrix": opencv_to_opengl(reader.poses[i]).tolist(),
                               "timestamp": float(reader.timestamps[i])}
        if depth_reader is not None:
            f = depth_reader.frame(i)
            if depth is not None:
                rel = DEPTH_DIR / f"{reader.frame_names[i]}.{'npy' if depth == 'npy' else 'png'}"
                data = _encode_depth(f["depth"], depth, reader.file("depth", i))
                if depth == "npy":
                    write_bytes(out_dir / rel, data)
                else:
                    write_png16(out_dir / rel, data)
                rec["depth_file_path"] = rel.as_posix()
            if point_stride:
                s = sample_depth_points(depth_reader, i, int(point_stride), frame=f)
                cloud_xyz.append(s["xyz"])
                cloud_rgb.append(s["rgb"])
        frames.append(rec)
    doc: dict[str, Any] = {
        "camera_model": "PINHOLE",
        "fl_x": ci["fx"], "fl_y": ci["fy"], "cx": ci["cx"] + PIXEL_OFFSET, "cy": ci["cy"] + PIXEL_OFFSET,
        "w": ci["width"], "h": ci["height"],
        "camera_angle_x": 2 * math.atan(ci["width"] / (2 * ci["fx"])),
        "camera_angle_y": 2 * math.atan(ci["height"] / (2 * ci["fy"])),
        "frames": frames,
        "room": {"camera": "OpenGL (x right, y up, z back), transform_matrix camera-to-world",
                 "world": "CT frame RAS+, metres", "pixel_centre": "top-left pixel centre at (0.5, 0.5)",
                 "source": f"{reader.path.parent.name}/{reader.name}", "images": images,
                 "depth": None if depth is None else "planar z-depth, 0 = none"},
    }
    if depth is not None:
        doc["depth_unit_scale_factor"] = PNG16_DEPTH_UNIT_M if depth == "png16" else 1.0
    n_points = 0
    if point_stride:
        xyz = np.concatenate(cloud_xyz).astype(np.float32)
        rgb = np.concatenate(cloud_rgb)
        n_points = len(xyz)
        write_ply(out_dir / PLY_NAME, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                       "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]},
                  comments=("room-pipeline sparse points sampled from the ground-truth depth maps",
                            "frame: world RAS+; units: m"))
        doc["ply_file_path"] = PLY_NAME
    write_json(out_dir / "transforms.json", doc)
    return {"transforms": "transforms.json", "frames": len(frames), "depth": depth, "points": n_points}


def read_transforms(path: str | os.PathLike) -> dict[str, Any]:
    """Parse a ``transforms.json`` (a file or its folder) back into the project's conventions.

    Returns ``file_paths`` (list of str, as written), ``poses`` (N, 4, 4) float64 camera-to-world
    with an **OpenCV** camera (the inverse of the export's conversion), ``K`` (3, 3) with the
    OpenCV pixel convention (``cx - 0.5``), ``width``, ``height``, ``depth_file_paths`` (list or
    None), ``depth_unit_scale_factor`` (float or None) and ``timestamps`` (N,) or None.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "transforms.json"
    if not p.is_file():
        raise InputError(f"transforms.json not found: {p}")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
        frames = doc["frames"]
        gl = np.array([f["transform_matrix"] for f in frames], dtype=np.float64).reshape(-1, 4, 4)
        K = np.array([[float(doc["fl_x"]), 0.0, float(doc["cx"]) - PIXEL_OFFSET],
                      [0.0, float(doc["fl_y"]), float(doc["cy"]) - PIXEL_OFFSET], [0.0, 0.0, 1.0]])
        size = (int(doc["w"]), int(doc["h"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{p}: not a transforms.json with fl_x, fl_y, cx, cy, w, h and frames ({exc})") from None
    depths = [f.get("depth_file_path") for f in frames]
    ts = [f.get("timestamp") for f in frames]
    return {"file_paths": [f["file_path"] for f in frames], "poses": opengl_to_opencv(gl), "K": K,
            "width": size[0], "height": size[1],
            "depth_file_paths": depths if all(d is not None for d in depths) else None,
            "depth_unit_scale_factor": doc.get("depth_unit_scale_factor"),
            "timestamps": np.array(ts, dtype=np.float64) if all(t is not None for t in ts) else None}
