"""The scene, described once and rendered by any backend (Open3D ray casting, Blender Cycles).

Everything is in world RAS+ metres; poses are camera-to-world (OpenCV camera).
The light sits at the camera (a bronchoscope's LEDs surround the lens), so
nothing the camera sees is in shadow: backends need no shadow rays.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..io.mesh import Mesh
from .camera import CameraIntrinsics


@dataclasses.dataclass(frozen=True)
class TissueMaterial:
    """Wet airway mucosa (Principled-BSDF-style parameters).

    base_color: linear RGB albedo in [0, 1]; roughness and specular as in
    Blender's Principled BSDF; subsurface_weight/subsurface_radius_m for
    optional subsurface scattering (Cycles only).
    """

    base_color: tuple[float, float, float] = (0.80, 0.38, 0.32)
    roughness: float = 0.35
    specular: float = 0.5
    subsurface_weight: float = 0.0
    subsurface_radius_m: tuple[float, float, float] = (1.0e-3, 0.4e-3, 0.25e-3)


@dataclasses.dataclass(frozen=True)
class TipLight:
    """Point light attached to the camera.

    power_w: radiant power in watts (Blender's point-light 'Power');
    offset_m: position in the camera frame (metres);
    radius_m: emitter radius (soft highlights);
    falloff: 'inverse_square' (physical) -- the only model both backends share.
    """

    power_w: float = 0.02
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius_m: float = 0.5e-3
    falloff: str = "inverse_square"


@dataclasses.dataclass
class Scene:
    """What to render: the lumen mesh, its material, the tip light, the camera and the poses.

    face_labels: optional (F,) int per-face label (e.g. airway branch id) for segmentation.
    timestamps: (T,) seconds; poses: (T, 4, 4) camera-to-world.
    """

    mesh: Mesh
    camera: CameraIntrinsics
    poses: np.ndarray
    timestamps: np.ndarray
    material: TissueMaterial = TissueMaterial()
    light: TipLight = TipLight()
    face_labels: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        if len(self.poses) != len(self.timestamps):
            raise ValueError(f"{len(self.poses)} poses but {len(self.timestamps)} timestamps")
