"""Per-frame point clouds of a rendered sequence as binary PLY files (Open3D, MeshLab, CloudCompare read them).

``points/frame_NNNN.ply``: the frame's point cloud as :class:`~room_pipeline.dataset.SequenceReader`
gives it -- the render stage's PLY when it wrote one, otherwise built on demand from the stored depth
(+ normals, RGB) -- every ``point_stride``-th row and column of the valid pixels (1 = all), in the
``frame``: ``camera`` (OpenCV, metres, as stored) or ``world`` (RAS+, metres, through the frame's
camera-to-world pose; normals rotated too).  Binary little-endian: float x, y, z; float nx, ny, nz;
uchar red, green, blue when present.  Header comments give the frame, units, index and pose.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..dataset.reader import SequenceReader
from ..errors import ConfigError
from ..io.ply import write_ply


def write_points(reader: SequenceReader, out_dir: Path, point_stride: int = 1, frame: str = "camera") -> dict[str, Any]:
    if frame not in ("camera", "world"):
        raise ConfigError(f"export ply: frame must be 'camera' or 'world', got {frame!r}")
    if int(point_stride) < 1:
        raise ConfigError(f"export ply: point_stride must be >= 1, got {point_stride!r}")
    src = SequenceReader(reader.path, ["point_cloud"], point_cloud_stride=int(point_stride))
    out = Path(out_dir) / "points"
    counts = []
    for i in range(len(src)):
        f = src.frame(i)
        p = f["point_cloud"].astype(np.float64)
        n = f.get("point_cloud_normals")
        pose = f["pose"]
        if frame == "world":
            p = p @ pose[:3, :3].T + pose[:3, 3]
            n = None if n is None else n.astype(np.float64) @ pose[:3, :3].T
        vertex = {"x": p[:, 0].astype(np.float32), "y": p[:, 1].astype(np.float32), "z": p[:, 2].astype(np.float32)}
        if n is not None:
            vertex.update(nx=n[:, 0].astype(np.float32), ny=n[:, 1].astype(np.float32), nz=n[:, 2].astype(np.float32))
        if "point_cloud_colors" in f:
            c = f["point_cloud_colors"]
            vertex.update(red=c[:, 0], green=c[:, 1], blue=c[:, 2])
        where = ("OpenCV camera (x right, y down, z forward)" if frame == "camera" else "world RAS+")
        write_ply(out / f"{f['name']}.ply", vertex,
                  comments=(f"room-pipeline point cloud of {f['name']}; frame: {where}; units: m",
                            f"frame_index {f['index']}; stride {int(point_stride)}",
                            "camera_to_world " + " ".join(repr(float(x)) for x in pose.reshape(-1))))
        counts.append(len(p))
    return {"points": "points/frame_NNNN.ply", "frame": frame, "point_stride": int(point_stride),
            "points_per_frame_mean": float(np.mean(counts)) if counts else 0.0}
