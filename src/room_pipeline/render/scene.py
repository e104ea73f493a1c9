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
from .texture import MucosaTexture, mucosa_albedo


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
    texture: MucosaTexture | None = None
    #: ray caster only (Cycles traces the inter-reflections): the wall-to-wall light it adds,
    #: :func:`~room_pipeline.render.shading.interreflection` (0 = single bounce)
    interreflection: float = 0.0
    interreflection_window_m: float = 0.006

    def __post_init__(self) -> None:
        if not 0.0 <= self.interreflection < 1.0 or not self.interreflection_window_m > 0:
            raise ValueError(f"material: 0 <= interreflection < 1 and interreflection_window > 0 required, got "
                             f"{self.interreflection}, {self.interreflection_window_m}")


@dataclasses.dataclass(frozen=True)
class TipLight:
    """Point light attached to the camera.

    power_w: radiant power in watts (Blender's point-light 'Power');
    offset_m: position in the camera frame (metres);
    radius_m: emitter radius (soft highlights);
    falloff: 'inverse_square' (physical; what Cycles renders) or 'exponential'
        (ray caster only): irradiance ``I cos exp(-r / falloff_length_m) / falloff_length_m^2``
        in place of ``I cos / r^2`` (the ROOM paper's exponential light falloff option);
    spot_exponent: angular emission profile ``cos(angle to the optical axis)^spot_exponent``
        (0 = isotropic point light; EndoMapper's photometric calibration of an
        endoscope fits a spot light with mu = 2.767, about 1.1 mm off the optical
        centre: endomapper/EM_Dataset-PhotometricCalibration).
    """

    power_w: float = 0.02
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius_m: float = 0.5e-3
    falloff: str = "inverse_square"
    falloff_length_m: float = 0.02
    spot_exponent: float = 0.0

    def __post_init__(self) -> None:
        if self.falloff not in ("inverse_square", "exponential"):
            raise ValueError(f"light falloff must be 'inverse_square' or 'exponential', got {self.falloff!r}")
        if not self.falloff_length_m > 0 or not self.spot_exponent >= 0 or not self.power_w >= 0:
            raise ValueError("light: falloff_length_m > 0, spot_exponent >= 0 and power_w >= 0 required")


@dataclasses.dataclass(frozen=True)
class Film:
    """Exposure and view transform (Cycles: Film / Color Management).

    exposure_ev: pixel = outgoing radiance * 2**exposure_ev (Blender's
        Color Management 'Exposure'); ``None`` = *automatic-fixed*: chosen
        once per sequence on ``auto_reference_frame`` so that the
        ``auto_percentile``-th percentile of the luminance of the surface
        pixels maps to ``auto_target`` (linear), then kept for every frame (no
        flicker; the chosen value is reported so another backend can use it).
    view_transform: 'standard' -- the sRGB transfer function, values clipped
        to [0, 1], 8-bit (Blender's 'Standard' view transform, look 'None').
    frame_ev: per-frame exposures (one per pose; the scope's automatic gain
        control, :func:`room_pipeline.render.exposure.exposure_track`); when
        set they replace ``exposure_ev``.
    response: camera response curve 'srgb' (Blender 'Standard') or 'gamma'
        (``v = x^(1/gamma)``; EndoMapper calibrates gamma 2.2), ray caster only.
    vignetting: lens vignetting ``cos(off-axis angle)^vignetting`` on the
        image (0 = none; natural vignetting of a pinhole is 4).
    veiling_glare: stray light in the lens spread evenly over the sensor:
        pixel = ``(1 - g) x + g mean(x)`` per channel over the frame (energy kept);
        lifts the dark lumen the way scattered light does in a real scope (and
        stands in for the inter-reflections a single-bounce renderer omits).
    """

    exposure_ev: float | None = None
    auto_reference_frame: int = 0
    auto_percentile: float = 95.0
    auto_target: float = 0.8
    view_transform: str = "standard"
    frame_ev: tuple | None = None
    response: str = "srgb"
    gamma: float = 2.2
    vignetting: float = 0.0
    veiling_glare: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.veiling_glare < 1:
            raise ValueError(f"film.veiling_glare must be in [0, 1), got {self.veiling_glare}")
        if self.response not in ("srgb", "gamma"):
            raise ValueError(f"film.response must be 'srgb' or 'gamma', got {self.response!r}")
        if not self.gamma > 0 or not self.vignetting >= 0:
            raise ValueError("film: gamma > 0 and vignetting >= 0 required")

    def ev(self, i: int, fixed: float) -> float:
        """Exposure of frame ``i``: the per-frame automatic exposure when set, else ``fixed``."""
        return float(self.frame_ev[i]) if self.frame_ev is not None else float(fixed)


@dataclasses.dataclass
class Scene:
    """What to render: the lumen mesh, its material, the tip light, the camera and the poses.

    face_labels: optional (F,) int per-face label (e.g. airway branch id) for segmentation.
    timestamps: (T,) seconds; poses: (T, 4, 4) camera-to-world.
    film: exposure and view transform (:class:`Film`).
    vertex_airway: optional (V, 4) airway coordinates of the mesh vertices
        (:func:`~room_pipeline.render.texture.airway_coordinates`): arc length
        mm, cos/sin of the angle about the centreline, generation.
    """

    mesh: Mesh
    camera: CameraIntrinsics
    poses: np.ndarray
    timestamps: np.ndarray
    material: TissueMaterial = TissueMaterial()
    light: TipLight = TipLight()
    face_labels: np.ndarray | None = None
    film: Film = Film()
    vertex_airway: np.ndarray | None = None
    _albedo_cache: tuple | None = dataclasses.field(default=None, init=False, repr=False, compare=False)

    def vertex_albedo(self) -> np.ndarray | None:
        """Per-vertex linear RGB albedo (V, 3) float32 from ``material.texture``, or None when untextured.

        The one place the texture is evaluated (both backends read it):
        :func:`~room_pipeline.render.texture.mucosa_albedo` at the mesh
        vertices (world metres) with ``material.base_color`` as the mean;
        computed once and cached (keyed on the material and the vertex array).
        Detail below the vertex spacing is not represented.
        """
        tex = self.material.texture
        if tex is None or not tex.enabled:
            return None
        key = (self.material, id(self.mesh.vertices), len(self.mesh.vertices))
        if self._albedo_cache is None or self._albedo_cache[0] != key:
            alb = mucosa_albedo(self.mesh.vertices, tex, base_color=self.material.base_color,
                                airway=self.vertex_airway)
            alb.setflags(write=False)
            self._albedo_cache = (key, alb)
        return self._albedo_cache[1]

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        if self.vertex_airway is not None:
            self.vertex_airway = np.asarray(self.vertex_airway, dtype=np.float32).reshape(-1, 4)
            if len(self.vertex_airway) != self.mesh.n_vertices:
                raise ValueError(f"vertex_airway has {len(self.vertex_airway)} rows for {self.mesh.n_vertices} vertices")
        if len(self.poses) != len(self.timestamps):
            raise ValueError(f"{len(self.poses)} poses but {len(self.timestamps)} timestamps")
