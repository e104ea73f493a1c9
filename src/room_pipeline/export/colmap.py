"""COLMAP text model of a rendered sequence with the ground-truth poses (no reconstruction is run).

Layout written into the export folder (the usual COLMAP / 3D Gaussian Splatting workspace)::

    images/frame_NNNN.png        copies of the sequence's rgb (or rgb_noisy) frames
    sparse/0/cameras.txt         one PINHOLE camera
    sparse/0/images.txt          one image per frame: world-to-camera pose, 2-D observations
    sparse/0/points3D.txt        sparse points sampled from the ground-truth depth maps (or empty)

Conventions (COLMAP's, converted from the project's)
    COLMAP's camera frame is the OpenCV one (x right, y down, z forward), so rotations carry over;
    COLMAP stores the **world-to-camera** transform ``x_cam = R x_world + t`` as the unit
    quaternion ``QW QX QY QZ`` (Hamilton, scalar first; written with ``QW >= 0``) and ``TX TY TZ``
    (metres, world RAS+).  From a camera-to-world pose ``[R_cw | c]``: ``R = R_cw^T``,
    ``t = -R c`` (with ``R`` rebuilt from the written quaternion, so the camera centre comes back
    exactly).  Intrinsics: model ``PINHOLE`` with ``fx fy cx cy`` in pixels, where COLMAP puts
    the **centre** of the top-left pixel at (0.5, 0.5) and the project (OpenCV) at (0, 0), so
    ``cx_colmap = cx + 0.5`` and ``cy_colmap = cy + 0.5``; 2-D points likewise get +0.5.
    Numbers are written with Python's shortest round-trip ``repr``: reading the text back gives
    the same doubles.

points3D.txt
    With ``point_stride = s > 0``: in every frame, the pixels ``(u, v)`` on the grid
    ``u, v = s//2, s//2 + s, ...`` that hit the surface are back-projected with the ground-truth
    depth, ``X = pose @ (depth K^-1 [u, v, 1])``, and written as one 3-D point each with the
    frame's colour at that pixel (mid grey without RGB), reprojection error 0 and a track of
    length one (the frame it was sampled in; the same surface point sampled in two frames is two
    points).  These are *not* triangulated feature tracks: they initialise methods that need a
    point cloud (3D Gaussian Splatting) and let a viewer show the geometry.  ``point_stride = 0``
    writes an empty points3D.txt and no 2-D observations.
"""
from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ..catalog import FOLDERS, RGB_SOURCES
from ..errors import ConfigError, InputError
from ..io.atomic import write_bytes, write_text
from ..dataset.reader import SequenceReader

#: pixel-centre offset between COLMAP (top-left pixel centre at 0.5) and OpenCV (at 0)
COLMAP_PIXEL_OFFSET = 0.5
SPARSE_DIR = Path("sparse") / "0"
IMAGES_DIR = Path("images")
GREY = (128, 128, 128)


def _r(x: float) -> str:
    return repr(float(x))


def world_to_camera(pose_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world 4x4 -> COLMAP's (quaternion (w, x, y, z) with w >= 0, translation t), world-to-camera."""
    pose = np.asarray(pose_c2w, dtype=np.float64)
    q = Rotation.from_matrix(pose[:3, :3].T).as_quat()           # x, y, z, w of R = R_cw^T
    if q[3] < 0:
        q = -q
    R = Rotation.from_quat(q).as_matrix()
    t = -R @ pose[:3, 3]
    return np.array([q[3], q[0], q[1], q[2]]), t


def camera_to_world(qvec_wxyz: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Inverse of :func:`world_to_camera`: COLMAP (qw, qx, qy, qz), t -> camera-to-world 4x4."""
    q = np.asarray(qvec_wxyz, dtype=np.float64)
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ np.asarray(tvec, dtype=np.float64)
    return T


def check_pinhole(reader: SequenceReader) -> None:
    d = reader.intrinsics["distortion"]
    if any(float(x) != 0.0 for x in d):
        raise InputError(f"{reader.path}: distortion {list(d)} is not zero; "
                         "the PINHOLE export needs an ideal pinhole camera")


def sample_depth_points(reader: SequenceReader, i: int, stride: int, frame: dict | None = None
                        ) -> dict[str, np.ndarray]:
    """Grid samples of frame ``i``'s depth map (see the module docstring).

    Returns ``uv`` (N, 2) float64 OpenCV pixel coordinates, ``xyz`` (N, 3) float64 world points
    (metres) and ``rgb`` (N, 3) uint8, ordered row-major over the grid.  ``frame``: the
    reader's frame dict when already loaded (must hold ``depth``; ``rgb`` is used when present).
    """
    f = frame if frame is not None else reader.frame(i)
    depth = f["depth"]
    h, w = depth.shape
    s = int(stride)
    vv, uu = np.mgrid[s // 2:h:s, s // 2:w:s]
    d = depth[vv, uu].astype(np.float64)
    keep = d > 0
    u, v, d = uu[keep].astype(np.float64), vv[keep].astype(np.float64), d[keep]
    K = f["K"]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d], axis=1)
    pose = f["pose"]
    xyz = cam @ pose[:3, :3].T + pose[:3, 3]
    rgb = f["rgb"][vv[keep], uu[keep]] if "rgb" in f else np.tile(np.array(GREY, np.uint8), (len(d), 1))
    return {"uv": np.stack([u, v], axis=1), "xyz": xyz, "rgb": np.asarray(rgb, dtype=np.uint8)}


def copy_images(reader: SequenceReader, out_dir: Path, source: str) -> list[str]:
    """Copy every frame's PNG of ``source`` (rgb or rgb_noisy) to ``out_dir/images``; the file names."""
    if source not in RGB_SOURCES:
        raise ConfigError(f"images must be 'rgb', 'rgb_noisy' or None, got {source!r}")
    folder = reader.path / FOLDERS[source]
    if not folder.is_dir():
        raise InputError(f"{folder} does not exist (images={source!r})")
    names = []
    for i in range(len(reader)):
        src = reader.file(source, i)
        if not src.is_file():
            raise InputError(f"image not found: {src}")
        write_bytes(out_dir / IMAGES_DIR / src.name, src.read_bytes())
        names.append(src.name)
    return names


def write_colmap(reader: SequenceReader, out_dir: Path, images: str | None = "rgb", point_stride: int = 16
                 ) -> dict[str, Any]:
    """Write the COLMAP text model (and the image copies) of ``reader``'s sequence into ``out_dir``."""
    check_pinhole(reader)
    if int(point_stride) < 0:
        raise ConfigError(f"point_stride must be >= 0 (0 = no points), got {point_stride}")
    if int(point_stride) > 0 and not (reader.path / FOLDERS["depth"]).is_dir():
        raise InputError(f"{reader.path / FOLDERS['depth']} does not exist: points3D.txt is sampled from the "
                         "depth maps (export with point_stride=0 for an empty one)")
    out_dir = Path(out_dir)
    if images is not None:
        copy_images(reader, out_dir, images)
    ci = reader.intrinsics
    o = COLMAP_PIXEL_OFFSET
    cameras = ("# Camera list with one line of data per camera:\n"
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
               "# Number of cameras: 1\n"
               f"1 PINHOLE {ci['width']} {ci['height']} {_r(ci['fx'])} {_r(ci['fy'])} "
               f"{_r(ci['cx'] + o)} {_r(ci['cy'] + o)}\n")
    sampler = None
    if point_stride:
        has_rgb = (reader.path / FOLDERS["rgb"]).is_dir()
        sampler = SequenceReader(reader.path, ["depth", "rgb"] if has_rgb else ["depth"])
    img_lines: list[str] = []
    pts = io.StringIO()
    n_points = 0
    for i in range(len(reader)):
        q, t = world_to_camera(reader.poses[i])
        name = f"{reader.frame_names[i]}.png"
        img_lines.append(f"{i + 1} {' '.join(_r(x) for x in q)} {' '.join(_r(x) for x in t)} 1 {name}")
        obs = []
        if sampler is not None:
            s = sample_depth_points(sampler, i, int(point_stride))
            for k, ((u, v), X, c) in enumerate(zip(s["uv"], s["xyz"], s["rgb"])):
                n_points += 1
                obs.append(f"{_r(u + o)} {_r(v + o)} {n_points}")
                pts.write(f"{n_points} {_r(X[0])} {_r(X[1])} {_r(X[2])} {int(c[0])} {int(c[1])} {int(c[2])} "
                          f"0.0 {i + 1} {k}\n")
        img_lines.append(" ".join(obs))
    n = len(reader)
    images_txt = ("# Image list with two lines of data per image:\n"
                  "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                  "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                  f"# Number of images: {n}, mean observations per image: {_r(n_points / n)}\n"
                  + "\n".join(img_lines) + "\n")
    points_txt = ("# 3D point list with one line of data per point:\n"
                  "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                  f"# Number of points: {n_points}, mean track length: {1.0 if n_points else 0.0}\n"
                  + pts.getvalue())
    sparse = out_dir / SPARSE_DIR
    write_text(sparse / "cameras.txt", cameras)
    write_text(sparse / "images.txt", images_txt)
    write_text(sparse / "points3D.txt", points_txt)
    return {"model": SPARSE_DIR.as_posix(), "images": n, "points3D": n_points,
            "image_folder": IMAGES_DIR.as_posix() if images is not None else None}
