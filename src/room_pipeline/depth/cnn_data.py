"""Data of the depth CNN's experiment (:mod:`~room_pipeline.depth.cnn`): frames and depth maps to network
inputs and targets, the procedural tube set it is pretrained on, and the SimCol3D RGB-D pairs it is
evaluated on (lengths in metres; depth is z-depth, invalid pixels outside ``valid_range_m``)."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np

from ..conventions import MM
from ..errors import InputError
from ..io.images import read_png
from ..io.mesh import Mesh
from ..render.camera import CameraIntrinsics, look_at
from .base import Sample
from .metrics import valid_gt


#: SimCol3D depth PNGs: depth_cm = value / 255 / 256 * 20 (the challenge's own loader); intrinsics of its camera
SIMCOL_DEPTH_M_PER_UNIT = 0.20 / (255 * 256)
SIMCOL_CAMERA = CameraIntrinsics(475, 475, 227.6, 227.6, 237.5, 237.5, 1e-4, 0.2)


def to_input(rgb8: np.ndarray, size: int) -> np.ndarray:
    """(3, size, size) float32 in [0, 1]: the frame area-resized (aspect not kept)."""
    import cv2

    a = np.asarray(rgb8)
    if a.ndim != 3 or a.shape[2] < 3 or a.dtype != np.uint8:
        raise InputError(f"cnn input must be (H, W, 3) uint8, got {a.dtype} {a.shape}")
    r = cv2.resize(np.ascontiguousarray(a[..., :3]), (size, size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(r.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)


def to_target(depth: np.ndarray, size: int, valid_range_m: Sequence[float]) -> np.ndarray:
    """(size, size) float32 mean of the valid depth in each target pixel (0 where under half is valid)."""
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    v = valid_gt(d, valid_range_m).astype(np.float32)
    dv = cv2.resize(np.where(v > 0, d, 0).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    vv = cv2.resize(v, (size, size), interpolation=cv2.INTER_AREA)
    return np.where(vv > 0.5, dv / np.maximum(vv, 1e-6), 0).astype(np.float32)


@dataclasses.dataclass
class ArrayDataset:
    """Network-resolution inputs (N, 3, S, S) and targets (N, S, S) (0 = invalid), with provenance."""

    x: np.ndarray
    y: np.ndarray
    sources: list

    def __len__(self) -> int:
        return len(self.x)


def dataset_from_samples(samples: Sequence[Sample], size: int, valid_range_m: Sequence[float]) -> ArrayDataset:
    xs, ys = [], []
    for s in samples:
        xs.append(to_input(s.load_rgb(), size))
        ys.append(to_target(s.load_gt(), size, valid_range_m))
    if not xs:
        raise InputError("no training frames")
    return ArrayDataset(np.stack(xs), np.stack(ys), sorted({s.group for s in samples}))


def curved_tube(rng: np.random.Generator, n_s: int = 72, n_theta: int = 48):
    """A random bent, bulging tube (open ends) and its centreline: (Mesh, centre(s), tangent(s), s samples, radius)."""
    length = rng.uniform(60, 120) * MM
    r0 = rng.uniform(3.0, 10.0) * MM
    kappa = rng.choice([-1, 1]) / (rng.uniform(25, 200) * MM)
    phi = rng.uniform(0, 2 * np.pi)
    u = np.array([np.cos(phi), np.sin(phi), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    b = np.cross(z, u)
    s = np.linspace(-5 * MM, length, n_s)
    ks = kappa * s
    centre = ((1 - np.cos(ks)) / kappa)[:, None] * u + (np.sin(ks) / kappa)[:, None] * z
    tangent = np.sin(ks)[:, None] * u + np.cos(ks)[:, None] * z
    normal = np.cos(ks)[:, None] * u - np.sin(ks)[:, None] * z
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    a1, lam, p1 = rng.uniform(0.0, 0.3), rng.uniform(10, 40) * MM, rng.uniform(0, 2 * np.pi)
    a2, m, p2 = rng.uniform(0.0, 0.15), rng.integers(2, 5), rng.uniform(0, 2 * np.pi)
    r = r0 * (1 + a1 * np.sin(2 * np.pi * s / lam + p1))[:, None] * (1 + a2 * np.cos(m * th + p2))[None, :]
    v = centre[:, None, :] + r[..., None] * (np.cos(th)[None, :, None] * normal[:, None, :]
                                             + np.sin(th)[None, :, None] * b[None, None, :])
    idx = np.arange(n_s * n_theta).reshape(n_s, n_theta)
    a_, b_ = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c_, d_ = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a_, b_, c_], -1).reshape(-1, 3), np.stack([b_, d_, c_], -1).reshape(-1, 3)])
    return Mesh(v.reshape(-1, 3), faces), centre, tangent, s, r0


def synthetic_tube_set(n_scenes: int, views: int, size: int, seed: int, valid_range_m: Sequence[float],
                       render_scale: int = 2) -> ArrayDataset:
    """The pretraining data: ``n_scenes`` random tubes x ``views`` camera poses inside each, rendered with the
    fast renderer at ``render_scale * size`` and area-downscaled like the real sequences (deterministic in ``seed``).
    """
    from ..render.raycast import RaycastRenderer
    from ..render.scene import Film, Scene, TipLight, TissueMaterial

    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for _ in range(n_scenes):
        mesh, centre, tangent, s, r0 = curved_tube(rng)
        fov = rng.uniform(75.0, 95.0)
        cam = CameraIntrinsics.from_fov(size * render_scale, size * render_scale, fov, 0.1 * MM, 0.5)
        poses = []
        for _ in range(views):
            j = int(rng.integers(1, len(s) // 3))
            radial = rng.normal(size=3)
            radial -= np.dot(radial, tangent[j]) * tangent[j]
            radial *= rng.uniform(0, 0.4) * r0 / max(np.linalg.norm(radial), 1e-12)
            axis = rng.normal(size=3)
            fwd = tangent[j] + np.tan(np.radians(rng.uniform(0, 25))) * (axis - np.dot(axis, tangent[j]) * tangent[j]) \
                / max(np.linalg.norm(axis - np.dot(axis, tangent[j]) * tangent[j]), 1e-12)
            poses.append(look_at(centre[j] + radial, fwd, rng.normal(size=3)))
        base = np.clip(np.array([0.80, 0.50, 0.54]) + rng.uniform(-0.15, 0.15, 3), 0.05, 1.0)
        scene = Scene(mesh, cam, np.array(poses), np.arange(views) * 0.1,
                      material=TissueMaterial(base_color=tuple(base), roughness=rng.uniform(0.25, 0.6)),
                      light=TipLight(power_w=0.02), film=Film(auto_target=rng.uniform(0.3, 0.8)))
        renderer = RaycastRenderer(scene)
        for i in range(views):
            out = renderer.render(i, ("rgb", "depth"))
            xs.append(to_input(out["rgb"], size))
            ys.append(to_target(np.where(out["hit"], out["depth"], 0), size, valid_range_m))
    return ArrayDataset(np.stack(xs), np.stack(ys), [f"synthetic tubes, seed {seed}"])


def read_simcol(folder: str | Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """SimCol3D pairs ``FrameBuffer_NNNN.png`` / ``Depth_NNNN.png``: (name, RGB uint8, planar depth metres).

    Depth: the challenge's loader divides the 16-bit value by 255 * 256 and
    multiplies by 20 cm (the values are multiples of 256: 8-bit precision,
    0.78 mm steps).  The frames are 16-bit RGBA; the top byte is the 8-bit value.
    """
    folder = Path(folder)
    pairs = []
    for f in sorted(folder.glob("FrameBuffer_*.png")):
        d = folder / f.name.replace("FrameBuffer_", "Depth_")
        if not d.is_file():
            continue
        rgb = read_png(f)
        rgb8 = (rgb[..., :3] >> 8).astype(np.uint8) if rgb.dtype == np.uint16 else rgb[..., :3].astype(np.uint8)
        depth = read_png(d)
        if depth.ndim == 3:
            depth = depth[..., 0]
        pairs.append((f.stem, rgb8, depth.astype(np.float32) * np.float32(SIMCOL_DEPTH_M_PER_UNIT)))
    return pairs


def simcol_samples(folder: str | Path, group: str = "simcol") -> list[Sample]:
    """The SimCol pairs as evaluation samples (one median-scaling group)."""
    pairs = read_simcol(folder)
    return [Sample(group, i, name, SIMCOL_CAMERA, (lambda a=rgb: a), (lambda a=depth: a))
            for i, (name, rgb, depth) in enumerate(pairs)]
