"""Typed records of the sequence files: one parser of the camera poses that three files store.

The planned trajectory (``metadata/trajectory.json``, key ``pose``), the simulated run
(``metadata/simulation.json``, key ``tip_pose``) and the render record (``metadata/render.json``,
key ``pose``) each hold per-frame camera-to-world 4x4 poses (OpenCV camera, world RAS+, metres)
with a ``timestamp`` in seconds; the planned one also an ``arclength`` in metres.
:func:`pose_track` reads any of them into a :class:`PoseTrack` (a malformed file is one
:class:`~room_pipeline.errors.InputError` line naming it).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..catalog import RENDER_JSON, SIMULATION_JSON, TRAJECTORY_JSON
from ..errors import InputError

#: file name -> the per-frame key of its camera-to-world pose
POSE_KEY = {TRAJECTORY_JSON: "pose", SIMULATION_JSON: "tip_pose", RENDER_JSON: "pose"}


@dataclasses.dataclass(frozen=True)
class PoseTrack:
    """(T,) timestamps s, (T, 4, 4) camera-to-world poses, (T,) arclength m (None when not stored); a joint-space
    plan (``trajectory.joint_plan``) also stores the (T, 4, 4) path poses the shaft follows (``path_pose``) and the
    (T, 3) joints to command (``q``: q1 m, q2 rad, q3 m); None when not stored."""

    timestamps: np.ndarray
    poses: np.ndarray
    arclength: np.ndarray | None = None
    path_poses: np.ndarray | None = None
    joints: np.ndarray | None = None

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    def __len__(self) -> int:
        return len(self.timestamps)


def pose_track_from_doc(doc: Mapping[str, Any], key: str, where: str | Path = "document") -> PoseTrack:
    """The ``frames`` of a parsed trajectory / simulation / render document as a :class:`PoseTrack`."""
    try:
        frames = doc["frames"]
        ts = np.array([f["timestamp"] for f in frames], dtype=np.float64).reshape(-1)
        poses = np.array([f[key] for f in frames], dtype=np.float64)
        arc = (np.array([f["arclength"] for f in frames], dtype=np.float64).reshape(-1)
               if frames and all("arclength" in f for f in frames) else None)
        path_poses = (np.array([f["path_pose"] for f in frames], dtype=np.float64)
                      if frames and all("path_pose" in f for f in frames) else None)
        joints = (np.array([f["q"] for f in frames], dtype=np.float64)
                  if frames and all("q" in f for f in frames) else None)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputError(f"{where}: frames need 'timestamp' and a 4x4 '{key}' ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())})") from None
    if len(ts) and (poses.ndim != 3 or poses.shape[1:] != (4, 4)):
        raise InputError(f"{where}: '{key}' of shape {poses.shape[1:]}, expected 4x4")
    if len(ts) == 0:
        poses = np.zeros((0, 4, 4))
    if path_poses is not None and path_poses.shape != poses.shape:
        raise InputError(f"{where}: 'path_pose' of shape {path_poses.shape}, expected {poses.shape}")
    if joints is not None and joints.shape != (len(ts), 3):
        raise InputError(f"{where}: 'q' of shape {joints.shape}, expected ({len(ts)}, 3)")
    return PoseTrack(ts, poses, arc, path_poses, joints)


def pose_track(path: str | Path, doc: Mapping[str, Any] | None = None) -> PoseTrack:
    """Read ``trajectory.json``, ``simulation.json`` or ``render.json`` (the key by the file's name);
    ``doc``: its already parsed content."""
    path = Path(path)
    if path.name not in POSE_KEY:
        raise InputError(f"{path}: not a pose file ({', '.join(POSE_KEY)})")
    if doc is None:
        import json

        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(f"cannot read {path} ({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    return pose_track_from_doc(doc, POSE_KEY[path.name], path)
