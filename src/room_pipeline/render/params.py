"""The render config (``conf/render/default.yaml``) as typed parameters, and what is built from it.

:class:`RenderParams` is the ``render`` section, checked whole by :meth:`RenderParams.from_dict` (one
:class:`~room_pipeline.errors.ConfigError` line); the helpers turn it into the camera
(:func:`camera_of`, lengths mm -> m), the scene's material, tip light and film (:func:`scene_parts`),
the automatic exposure's parameters, the ray caster's and Cycles' settings.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from ..catalog import RENDER_FOLDERS as FOLDERS  # modality -> folder
from ..config.params import params_from_dict
from ..conventions import MM
from ..errors import ConfigError
from ..io.storage import StorageParams
from .camera import CameraIntrinsics
from .scene import Film, TipLight, TissueMaterial
from .texture import MucosaTexture


@dataclasses.dataclass(frozen=True)
class RenderParams:
    """Keys of ``conf/render/default.yaml`` (see its comments for units); defaults equal to it
    (``tests/test_conf_defaults.py``)."""

    backend: str = "raycast"
    poses: str = "simulated"
    modalities: tuple = ("rgb", "depth", "relative_depth", "normals", "flow", "segmentation")
    frame_stride: int = 1
    max_frames: int | None = None
    width: int = 600
    height: int = 600
    fov_deg: float = 85.0
    near_mm: float = 0.1
    far_mm: float = 500.0
    distortion: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)
    base_color: tuple = (0.682, 0.518, 0.553)
    roughness: float = 0.35
    specular: float = 0.5
    interreflection: float = 0.0
    interreflection_window_mm: float = 6.0
    indirect_bounces: int = 8
    indirect_rays_per_point: int = 64
    indirect_seed: int = 0
    indirect_shadows: bool = True
    indirect_caustics: bool = False
    indirect_max_edge_mm: float = 2.0
    direct_shadows: bool = False
    light_power_w: float = 0.02
    light_radius_mm: float = 0.5
    light_offset_mm: tuple = (0.0, -1.1, 0.0)
    light_spot_exponent: float = 0.0
    light_falloff: str = "inverse_square"
    light_falloff_length_mm: float = 20.0
    exposure_ev: float | None = None
    auto_exposure: str = "per_frame"
    auto_exposure_target: float = 0.318
    auto_exposure_percentile: float = 95.0
    auto_exposure_smoothing_s: float = 0.3
    auto_exposure_min_ev: float = -12.0
    auto_exposure_max_ev: float = 12.0
    auto_exposure_highlight_percentile: float = 99.0
    auto_exposure_highlight_max: float = 0.9
    vignetting: float = 0.0
    veiling_glare: float = 0.0
    response: str = "srgb"
    gamma: float = 2.2
    shading_stride: int = 2
    edge_samples: int = 0
    edge_depth_jump: float = 0.15
    texture: dict = dataclasses.field(default_factory=dict)
    cycles_samples: int = 4
    cycles_denoise: bool = True
    cycles_bounces: int = 8
    storage: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "RenderParams":
        p = params_from_dict(cls, d, "render")
        if p.backend not in ("raycast", "cycles"):
            raise ConfigError(f"render.backend must be 'raycast' or 'cycles', got {p.backend!r}")
        if p.poses not in ("planned", "simulated"):
            raise ConfigError(f"render.poses must be 'planned' or 'simulated', got {p.poses!r}")
        bad = set(p.modalities) - set(FOLDERS)
        if bad:
            raise ConfigError(f"render.modalities: unknown {sorted(bad)} (known: {sorted(FOLDERS)})")
        if p.frame_stride < 1 or p.width < 8 or p.height < 8 or not 1.0 < p.fov_deg < 170.0:
            raise ConfigError(f"render: frame_stride >= 1, width/height >= 8 and 1 < fov_deg < 170 required, got "
                              f"frame_stride={p.frame_stride}, width={p.width}, height={p.height}, fov_deg={p.fov_deg}")
        if p.max_frames is not None and (isinstance(p.max_frames, bool) or not isinstance(p.max_frames, int)
                                         or p.max_frames < 1):
            raise ConfigError(f"render.max_frames must be null or an integer >= 1, got {p.max_frames!r}")
        if not 0.0 < p.near_mm < p.far_mm:
            raise ConfigError(f"render: 0 < near_mm < far_mm required, got near_mm={p.near_mm}, far_mm={p.far_mm}")
        camera_of(p)
        texture_params(p.texture)
        StorageParams.from_dict(p.storage)
        if p.auto_exposure not in ("per_frame", "first_frame"):
            raise ConfigError(f"render.auto_exposure must be 'per_frame' or 'first_frame', got {p.auto_exposure!r}")
        if len(p.light_offset_mm) != 3:
            raise ConfigError(f"render.light_offset_mm must be 3 numbers (camera frame, mm), got {p.light_offset_mm!r}")
        if p.shading_stride < 1:
            raise ConfigError(f"render.shading_stride must be >= 1, got {p.shading_stride}")
        if isinstance(p.cycles_bounces, bool) or not isinstance(p.cycles_bounces, int) or p.cycles_bounces < 0:
            raise ConfigError(f"render.cycles_bounces must be an integer >= 0, got {p.cycles_bounces!r}")
        if isinstance(p.edge_samples, bool) or not isinstance(p.edge_samples, int) or p.edge_samples < 0 \
                or not p.edge_depth_jump > 0:
            raise ConfigError(f"render: edge_samples must be an integer >= 0 and edge_depth_jump > 0, got "
                              f"{p.edge_samples!r}, {p.edge_depth_jump!r}")
        try:
            scene_parts(p)
            exposure_params(p)
            indirect_config(p)
        except ValueError as e:
            raise ConfigError(f"render: {str(e).splitlines()[0]}") from None
        return p


def camera_of(p: "RenderParams") -> CameraIntrinsics:
    """The render config's camera (lengths mm -> m); a distortion that is not a lens or that Cycles would
    have to render: ConfigError."""
    d = p.distortion
    if (isinstance(d, (str, bytes)) or not hasattr(d, "__len__") or len(d) != 5
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in d)):
        raise ConfigError(f"render.distortion must be 5 numbers (k1, k2, p1, p2, k3; OpenCV), got {d!r}")
    cam = CameraIntrinsics.from_fov(p.width, p.height, p.fov_deg, p.near_mm * MM, p.far_mm * MM, distortion=d)
    try:
        cam.check_distortion()
    except ValueError as e:
        raise ConfigError(f"render.distortion: {e}") from None
    if cam.has_distortion and p.backend == "cycles":
        raise ConfigError(f"render.distortion {list(cam.distortion)}: Cycles renders an ideal pinhole image only; "
                          "use render.backend=raycast or render.distortion=[0,0,0,0,0]")
    return cam


def exposure_params(p: "RenderParams"):
    """The per-frame automatic exposure's parameters (render.auto_exposure_*)."""
    from .exposure import ExposureParams

    return ExposureParams(target=p.auto_exposure_target, percentile=p.auto_exposure_percentile,
                          smoothing_s=p.auto_exposure_smoothing_s, min_ev=p.auto_exposure_min_ev,
                          max_ev=p.auto_exposure_max_ev, highlight_percentile=p.auto_exposure_highlight_percentile,
                          highlight_max=p.auto_exposure_highlight_max)


def scene_parts(p: "RenderParams") -> tuple[TissueMaterial, TipLight, Film]:
    """Material, tip light and film of the render config (lengths mm -> m)."""
    material = TissueMaterial(base_color=tuple(p.base_color), roughness=p.roughness, specular=p.specular,
                              texture=texture_params(p.texture), interreflection=p.interreflection,
                              interreflection_window_m=p.interreflection_window_mm * MM)
    light = TipLight(power_w=p.light_power_w, radius_m=p.light_radius_mm * MM,
                     offset_m=tuple(float(x) * MM for x in p.light_offset_mm), falloff=p.light_falloff,
                     falloff_length_m=p.light_falloff_length_mm * MM, spot_exponent=p.light_spot_exponent)
    film = Film(exposure_ev=p.exposure_ev, auto_target=p.auto_exposure_target,
                auto_percentile=p.auto_exposure_percentile, response=p.response, gamma=p.gamma,
                vignetting=p.vignetting, veiling_glare=p.veiling_glare)
    return material, light, film


def indirect_config(p: "RenderParams"):
    """The ray caster's precomputed inter-reflection (render.indirect_*; :mod:`room_pipeline.render.indirect`)."""
    from .indirect import IndirectConfig

    return IndirectConfig(bounces=p.indirect_bounces, rays_per_point=p.indirect_rays_per_point,
                          seed=p.indirect_seed, shadows=p.indirect_shadows, caustics=p.indirect_caustics,
                          max_edge_mm=p.indirect_max_edge_mm)


def raycast_config(p: "RenderParams", nthreads: int = 0):
    """The ray caster's configuration of the render config."""
    from .raycast import RaycastConfig

    return RaycastConfig(nthreads=nthreads, shading_stride=p.shading_stride, indirect=indirect_config(p),
                         direct_shadows=p.direct_shadows, edge_samples=p.edge_samples,
                         edge_depth_jump=p.edge_depth_jump)


def texture_params(d: Mapping[str, Any] | None) -> MucosaTexture:
    """The ``render.texture`` section as a :class:`MucosaTexture` (unknown key or bad value: ConfigError)."""
    if d is not None and not isinstance(d, Mapping):
        raise ConfigError(f"render.texture must be a mapping, got {d!r}")
    try:
        return params_from_dict(MucosaTexture, d, "render.texture")
    except ValueError as e:
        raise ConfigError(str(e).splitlines()[0]) from None


def cycles_settings(p: RenderParams, **kw: Any):
    from .blender import CyclesSettings

    return CyclesSettings.from_dict({"samples": p.cycles_samples, "denoise": p.cycles_denoise,
                                     "max_bounces": p.cycles_bounces, **kw})
