"""Photoreal backend: Blender Cycles (CPU) through ``bpy``, built from the backend-agnostic :class:`Scene`.

This is the only module of room-pipeline that imports ``bpy`` (Blender 5.0 as a
Python module).  ``bpy`` is imported lazily, when a :class:`CyclesRenderer` is
built, so importing this module is cheap.  Never import ``pymeshlab`` (or
``room_pipeline.anatomy.mesh``) before ``bpy`` in the same process: their
Embree builds clash and Cycles breaks (see ``DESIGN.md``).  ``bpy`` holds one
global Blender session per process, so only one :class:`CyclesRenderer` is live
at a time (building a new one factory-resets the session).

Over 500 lines because it is the bpy adapter and the only module allowed to import ``bpy`` (the Kubric rule
the import tests keep): building the scene, the tissue's shader nodes, the light, the camera and its
animation, the render passes and reading them back all call bpy, and split across modules each part would
need bpy too.

What is rendered (one Cycles render per frame, all passes at once):

``rgb``
    (H, W, 3) float32, linear scene-referred radiance (Cycles' Combined pass)
    times ``2**exposure_ev`` (settings, else ``Scene.film``, else
    automatic-fixed as in the fast renderer); :func:`linear_to_srgb8` converts it to an 8-bit
    sRGB image (the 'Standard' view transform, clipped).
``depth``
    (H, W) float32 planar z in metres; 0 where the ray hit nothing.  Cycles
    writes its Depth pass (planar z) from a single camera ray through the
    pixel centre, not a filter average (checked in the tests: the coverage of
    a rectangle is binary and exactly the OpenCV pixel centres inside it), so
    silhouette pixels carry the depth of one surface, never a mix.
``normals``
    (H, W, 3) float32 unit shading normals in the OpenCV camera frame, facing
    the camera (``n . ray < 0``: from the wall into the lumen, the opposite of
    the mesh's air-to-tissue orientation -- the convention of the fast
    renderer, raycast.py); smooth (interpolated vertex) normals by default;
    0 where nothing was hit.  Cycles' Normal pass is world-space and
    accumulated over the samples; it is renormalised and rotated by R^T.
``flow``
    (H, W, 2) float32 forward optical flow frame t -> t+1 in pixels, OpenCV
    image axes (u right, v down), from Cycles' Vector pass; ``None`` for the
    last frame (no t+1 pose).  Rendered frames' :attr:`CyclesRenderer.notes`
    carry the reason when a modality is ``None``.

Blender's Vector pass convention (Cycles, motion blur off; checked
numerically in ``tests/test_blender.py``): 4 channels in raster pixels with
Blender's raster y pointing *up* (row 0 at the bottom).  For the surface point
seen at a pixel at frame t, X,Y = p(t) - p(t-1) (motion *from* the previous
frame) and Z,W = p(t) - p(t+1) (minus the motion *to* the next frame), where
p(f) is the point's raster position with the camera of frame f.  So forward
flow in OpenCV axes is (u, v) = (-Z, +W).  Blender takes the camera of frames
f-1 and f+1 from the animation; we keyframe the camera at every pose.  The
flow is that of the point visible at t, occluded or not at t+1 (no occlusion
mask: :mod:`room_pipeline.render.flow` makes one from depth).  Measured
against the geometric flow from ray-cast depth and the relative pose, the
end-point error is ~0.007 px mean (tests), so the product can write the
Cycles flow or the geometric flow interchangeably away from silhouettes; at
silhouettes Cycles' Vector pass is a filter-weighted average of the motions
of both surfaces (accumulated over samples), the geometric flow is that of
the surface at the pixel centre -- the dataset should write the geometric one
(it matches depth, which is per pixel centre) with its validity mask.

Texture: a textured :class:`Scene` (``material.texture``) is rendered with
the appearance function evaluated **per shading point** by default
(``CyclesSettings.texture = 'per_point'``): an OSL script node
(:mod:`room_pipeline.render.texture_osl`, compiled here with Cycles' own OSL
compiler; Cycles runs OSL on the CPU, ``shading_system``) computes
:func:`~room_pipeline.render.texture.mucosa_albedo` at the object-space hit
point, with the airway coordinates from two POINT-domain attributes
(interpolated barycentrically, as in the ray caster), and feeds the Principled
BSDF's Base Color -- the appearance the ray caster evaluates at every pixel.
``texture = 'vertex'``: the per-vertex bake (:meth:`Scene.vertex_albedo`) as a
linear ``FLOAT_COLOR`` POINT attribute (``ALBEDO_ATTRIBUTE``) read by an
Attribute node (detail below the vertex spacing lost; faster SVM shading).

Camera: a Blender camera looks down its local -z with +y up, the OpenCV camera
down +z with y down, so the Blender camera-to-world matrix is
``pose @ diag(1, -1, -1, 1)``.  Intrinsics: sensor fit 'HORIZONTAL', lens =
fx * sensor_width / W, pixel aspect fx/fy, principal point through
shift_x = -(cx - (W-1)/2) / W and shift_y = (cy - (H-1)/2) * (fx/fy) / W
(Blender's pixel centres are at half-integers, OpenCV's at integers).

Cycles' ``scene.cycles.seed`` and a fixed sampling pattern make renders
bit-for-bit repeatable on one machine and thread count.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import tempfile
import weakref
from pathlib import Path
from typing import Iterable

import numpy as np

from ..config.params import params_from_dict
from ..errors import ConfigError
from .scene import Scene

#: Modalities :meth:`CyclesRenderer.render` can return.
MODALITIES = ("rgb", "depth", "normals", "flow")

#: OpenCV camera axes -> Blender camera axes (and back: it is its own inverse).
CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])

#: Name of the mesh colour attribute holding the texture's per-vertex albedo (linear RGB).
ALBEDO_ATTRIBUTE = "mucosa_albedo"

#: How a textured Scene's albedo reaches Cycles (:attr:`CyclesSettings.texture`).
TEXTURE_MODES = ("per_point", "vertex")

#: Cycles writes this (1e10) in the Depth pass where a ray escapes.
_NO_HIT_DEPTH = 1e9


@dataclasses.dataclass(frozen=True)
class CyclesSettings:
    """Cycles quality/speed knobs.

    The defaults are the recommended preset (benchmarks/cycles_quality.md):
    4 spp + OpenImageDenoise, 3 bounces, no shadow rays -- about 42-44 dB PSNR
    against a noise-free estimate at 300x300 and ~5 s per 600x600 frame on 2
    shared CPU cores.

    samples: max samples per pixel; adaptive_threshold: Cycles' adaptive
    sampling noise threshold (0 disables adaptive sampling); adaptive_min_samples:
    0 = Cycles' automatic choice; denoise: OpenImageDenoise on the Combined pass
    (albedo + normal guides); max_bounces: total path depth (diffuse/glossy
    share it); cast_shadows: shadow rays for the tip light (the light sits at
    the camera, so visible surfaces are not shadowed; see the benchmark);
    exposure: stops applied to the linear result (``2**exposure``); ``None``
    (default) = the Scene's ``film.exposure_ev``, whose ``None`` means
    automatic-fixed: chosen once on the film's reference frame (rendered
    first) with :func:`room_pipeline.render.shading.auto_exposure_ev`, the
    rule of the fast renderer, then kept for the whole sequence; seed:
    Cycles' sampling seed; threads: CPU threads (0 = all); filter_width: pixel
    filter width in pixels (Blackman-Harris; affects RGB and the
    sample-averaged Normal and Vector passes; Depth is per pixel centre); smooth_shading: interpolated vertex normals (True) or flat faces;
    tile_size: Cycles tile size in pixels; denoise_prefilter: OIDN guide
    prefilter (NONE / FAST / ACCURATE: ACCURATE denoises the albedo and normal
    guides too, about 3x the denoiser time); denoise_quality: OIDN quality
    (FAST / BALANCED / HIGH); clamp_indirect: Cycles' ``sample_clamp_indirect`` (Blender's default 10;
    0 = no clamp: an unbiased reference, since near the tip light a bounced sample's radiance exceeds 10);
    filter_glossy: Cycles' ``blur_glossy`` (Blender's default 1.0; 0 = the glossy lobe keeps its roughness
    after a diffuse bounce, unbiased); texture: how a textured Scene's albedo reaches Cycles -- 'per_point'
    (the appearance function in OSL at every shading point) or 'vertex' (its per-vertex bake,
    interpolated).  The references of benchmarks/realism_indirect.py and the closed-sphere test use 0 and 0 (tests/test_indirect.py: with Blender's defaults the sphere renders ~3 % darker).
    """

    samples: int = 4
    adaptive_threshold: float = 0.01
    adaptive_min_samples: int = 0
    denoise: bool = True
    max_bounces: int = 3
    cast_shadows: bool = False
    exposure: float | None = None
    seed: int = 0
    threads: int = 0
    filter_width: float = 1.5
    smooth_shading: bool = True
    tile_size: int = 2048
    denoise_prefilter: str = "FAST"
    denoise_quality: str = "BALANCED"
    clamp_indirect: float = 10.0
    filter_glossy: float = 1.0
    texture: str = "per_point"

    def __post_init__(self) -> None:
        if self.exposure is not None:           # stops: a plain float (so to_dict() is JSON), or null
            try:
                if isinstance(self.exposure, bool):
                    raise TypeError
                object.__setattr__(self, "exposure", float(self.exposure))
            except (TypeError, ValueError):
                raise ConfigError(f"cycles.exposure: cannot read {self.exposure!r} as a number of stops") from None
        if self.samples < 1:
            raise ConfigError(f"cycles.samples must be >= 1, got {self.samples}")
        if not 0.0 <= self.adaptive_threshold < 1.0:
            raise ConfigError(f"cycles.adaptive_threshold must be in [0, 1), got {self.adaptive_threshold}")
        if self.max_bounces < 0:
            raise ConfigError(f"cycles.max_bounces must be >= 0, got {self.max_bounces}")
        if self.threads < 0:
            raise ConfigError(f"cycles.threads must be >= 0, got {self.threads}")
        if self.denoise_prefilter not in ("NONE", "FAST", "ACCURATE"):
            raise ConfigError(f"cycles.denoise_prefilter must be NONE, FAST or ACCURATE, got {self.denoise_prefilter!r}")
        if self.denoise_quality not in ("FAST", "BALANCED", "HIGH"):
            raise ConfigError(f"cycles.denoise_quality must be FAST, BALANCED or HIGH, got {self.denoise_quality!r}")
        if not (self.clamp_indirect >= 0.0 and self.filter_glossy >= 0.0):
            raise ConfigError(f"cycles.clamp_indirect and cycles.filter_glossy must be >= 0, got "
                              f"{self.clamp_indirect}, {self.filter_glossy}")
        if self.texture not in TEXTURE_MODES:
            raise ConfigError(f"cycles.texture must be one of {TEXTURE_MODES}, got {self.texture!r}")
        if not 0.01 <= self.filter_width <= 10.0:
            raise ConfigError(f"cycles.filter_width must be in [0.01, 10] px, got {self.filter_width}")

    @staticmethod
    def from_dict(d: dict | None) -> "CyclesSettings":
        """Build from a config mapping (:func:`~room_pipeline.config.params.params_from_dict`, section ``cycles``,
        then :meth:`__post_init__`); an unknown key or a bad value raises :class:`ConfigError` naming it."""
        return params_from_dict(CyclesSettings, d, "cycles")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: candela of the IES profile's peak at which Cycles' IES texture gives Fac = 1 on the axis (so the on-axis
#: intensity stays the point light's P / (4 pi)): measured on this Blender (a 1000 cd peak rendered 70.6x
#: the isotropic light); tests/test_realism.py::test_cycles_renders_the_same_scope_light_as_the_ray_caster
#: fails if a Blender update changes it.
IES_UNIT_CD = 1000.0 / 70.6


def import_bpy():
    """``import bpy`` (the only one of room-pipeline), also in a worker spawned by a process that had imported bpy.

    Importing bpy puts Blender's script folders (``.../site-packages/bpy/<ver>/scripts/...``) on
    ``sys.path``; a spawned process inherits that ``sys.path``, so its ``import bpy`` would find
    Blender's inner ``bpy`` package (which needs the ``_bpy`` built-in) instead of the bpy module.
    Until bpy is imported in this process, those folders are dropped.
    """
    if "bpy" not in sys.modules:
        marker = f"{os.sep}site-packages{os.sep}bpy{os.sep}"
        sys.path[:] = [d for d in sys.path if marker not in d]
    import bpy

    return bpy


def ies_profile(mu: float, n: int = 181) -> str:
    """An IES LM-63 photometric file with candela ``cos(theta)^mu`` (theta from the light's axis, 0..90 deg;
    0 beyond) times :data:`IES_UNIT_CD`: the tip light's angular emission
    (:class:`~room_pipeline.render.scene.TipLight`); its axis is the light's -Z, which is the camera's
    viewing direction (the light is parented to it)."""
    th = np.linspace(0.0, 180.0, n)
    cd = np.where(th < 90.0, np.cos(np.radians(np.minimum(th, 90.0))) ** float(mu), 0.0) * IES_UNIT_CD
    fmt = lambda a: " ".join(f"{x:.6g}" for x in a)  # noqa: E731
    return "\n".join(["IESNA:LM-63-2002", "[TEST] room-pipeline tip light cos^mu", "TILT=NONE",
                      f"1 -1 1 {n} 1 1 2 0 0 0", "1 1 0", fmt(th), "0", fmt(cd)]) + "\n"


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB (float) -> 8-bit sRGB (IEC 61966-2-1 transfer curve, clipped to [0, 1]), uint8."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def blender_camera_intrinsics(cam) -> dict:
    """Blender camera data settings that reproduce ``cam`` (a :class:`CameraIntrinsics`) exactly."""
    sensor_width = 36.0
    aspect_y = cam.fx / cam.fy  # Blender's ycor = pixel_aspect_y / pixel_aspect_x
    if aspect_y >= 1.0:
        pax, pay = 1.0, aspect_y
    else:
        pax, pay = 1.0 / aspect_y, 1.0
    # With pixel_aspect_x != 1 Blender scales x: keep fx by scaling the lens accordingly.
    lens = cam.fx * sensor_width / cam.width
    return {"sensor_fit": "HORIZONTAL", "sensor_width": sensor_width, "lens": lens,
            "pixel_aspect_x": pax, "pixel_aspect_y": pay,
            "shift_x": -(cam.cx - (cam.width - 1) / 2) / cam.width,
            "shift_y": (cam.cy - (cam.height - 1) / 2) * aspect_y / cam.width,
            "clip_start": cam.near, "clip_end": cam.far}


class CyclesRenderer:
    """Render a :class:`Scene` with Blender Cycles on the CPU.

    Builds the Blender scene once (factory reset, mesh, material, camera with
    one keyframe per pose, tip light parented to the camera, no world light);
    :meth:`render` then renders one frame per call with persistent data, so
    the BVH is built once.  Use as a context manager (or call :meth:`close`)
    to remove the temporary EXR folder.
    """

    def __init__(self, scene: Scene, settings: CyclesSettings | None = None, tmp_dir: str | os.PathLike | None = None,
                 vertex_normals: np.ndarray | None = None):
        self.scene = scene
        #: optional (V, 3) unit vertex normals for smooth shading, pointing into the lumen (the side Blender's
        #: faces show the camera), e.g. a subdivided mesh that keeps its parent's interpolated normals;
        #: None: Blender's own vertex normals
        self.vertex_normals = vertex_normals
        self.settings = settings or CyclesSettings()
        self._own_tmp = tmp_dir is None
        self.tmp_dir = Path(tempfile.mkdtemp(prefix="room_cycles_") if tmp_dir is None else tmp_dir)
        self.tmp_dir.mkdir(parents=True, exist_ok=True)
        if self._own_tmp:  # removed at close(), garbage collection or exit, whichever comes first
            self._finalizer = weakref.finalize(self, shutil.rmtree, str(self.tmp_dir), True)
        #: per-modality reason when the last :meth:`render` returned None for it
        self.notes: dict[str, str] = {}
        #: seconds spent in Blender's render call for the last frame
        self.last_render_s: float = float("nan")
        self._exposure_ev: float | None = None
        self._build()

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        bpy = import_bpy()
        self._bpy = bpy
        sc = self.scene
        st = self.settings
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bs = bpy.context.scene
        self._bscene = bs

        # --- mesh (flip the winding: Blender front faces look into the lumen, towards the camera)
        v = np.asarray(sc.mesh.vertices, dtype=np.float64)
        f = np.asarray(sc.mesh.faces, dtype=np.int64)[:, ::-1]
        me = bpy.data.meshes.new("lumen")
        me.vertices.add(len(v))
        me.vertices.foreach_set("co", v.astype(np.float32).ravel())
        me.loops.add(f.size)
        me.loops.foreach_set("vertex_index", f.astype(np.int32).ravel())
        me.polygons.add(len(f))
        me.polygons.foreach_set("loop_start", np.arange(0, f.size, 3, dtype=np.int32))
        me.update(calc_edges=True)
        me.validate(verbose=False)
        if st.smooth_shading:
            me.shade_smooth()
            if self.vertex_normals is not None:
                vn = np.asarray(self.vertex_normals, dtype=np.float64)
                if vn.shape != v.shape:
                    raise RuntimeError(f"vertex_normals {vn.shape} for {len(v)} vertices")
                me.normals_split_custom_set_from_vertices([tuple(x) for x in vn.tolist()])
        else:
            me.shade_flat()
        va = sc.vertex_albedo() if st.texture == "vertex" else None
        if self._per_point_texture() and sc.vertex_airway is not None:  # the OSL shader's airway coordinates
            _add_airway_attributes(me, sc.vertex_airway)
        if va is not None:  # the texture, baked per vertex: a linear float colour attribute (POINT domain)
            if len(va) != len(me.vertices):
                raise RuntimeError(f"Blender mesh has {len(me.vertices)} vertices, vertex albedo {len(va)}")
            attr = me.color_attributes.new(ALBEDO_ATTRIBUTE, "FLOAT_COLOR", "POINT")
            rgba = np.ones((len(va), 4), dtype=np.float32)
            rgba[:, :3] = va
            attr.data.foreach_set("color", rgba.ravel())
            me.update()
        obj = bpy.data.objects.new("lumen", me)
        bs.collection.objects.link(obj)
        obj.data.materials.append(self._material(bpy))
        self._mesh_obj = obj

        # --- camera, keyframed at every pose (the Vector pass needs frames f-1 and f+1)
        cd = bpy.data.cameras.new("scope")
        cam = bpy.data.objects.new("scope", cd)
        bs.collection.objects.link(cam)
        bs.camera = cam
        if sc.camera.has_distortion:   # Cycles' perspective camera is an ideal pinhole
            raise ConfigError(f"camera distortion {list(sc.camera.distortion)}: Cycles renders an ideal pinhole "
                              "image only (render.backend=raycast renders the lens distortion)")
        ci = blender_camera_intrinsics(sc.camera)
        for k in ("sensor_fit", "sensor_width", "lens", "shift_x", "shift_y", "clip_start", "clip_end"):
            setattr(cd, k, ci[k])
        cd.type = "PERSP"
        r = bs.render
        r.resolution_x, r.resolution_y, r.resolution_percentage = sc.camera.width, sc.camera.height, 100
        r.pixel_aspect_x, r.pixel_aspect_y = ci["pixel_aspect_x"], ci["pixel_aspect_y"]
        cam.rotation_mode = "QUATERNION"
        for i, pose in enumerate(sc.poses):
            self._set_camera(cam, pose)
            cam.keyframe_insert("location", frame=i)
            cam.keyframe_insert("rotation_quaternion", frame=i)
        if cam.animation_data and cam.animation_data.action:
            for fc in _fcurves(cam.animation_data.action):
                for kp in fc.keyframe_points:
                    kp.interpolation = "LINEAR"
        bs.frame_start, bs.frame_end = 0, max(0, len(sc.poses) - 1)
        self._cam = cam

        # --- tip light: point light parented to the camera at TipLight.offset (OpenCV camera frame)
        ld = bpy.data.lights.new("tip", "POINT")
        ld.energy = float(sc.light.power_w)
        ld.shadow_soft_size = float(sc.light.radius_m)
        ld.use_shadow = bool(st.cast_shadows)
        ld.use_soft_falloff = False  # physical inverse-square falloff (the Scene's only model)
        if sc.light.falloff != "inverse_square":
            raise ConfigError(f"TipLight.falloff {sc.light.falloff!r} not supported (inverse_square only)")
        light = bpy.data.objects.new("tip", ld)
        bs.collection.objects.link(light)
        light.parent = cam
        off = np.asarray(sc.light.offset_m, dtype=np.float64)
        light.location = (off[0], -off[1], -off[2])  # OpenCV camera frame -> Blender camera frame
        light.visible_camera = False  # the emitter sphere surrounds the lens; only its reflections show
        if sc.light.spot_exponent > 0:    # angular emission cos^mu about the optical axis: an IES profile
            ld.use_nodes = True
            nt = ld.node_tree
            ies = nt.nodes.new("ShaderNodeTexIES")
            ies.mode = "INTERNAL"
            txt = bpy.data.texts.new("tip_profile.ies")
            txt.write(ies_profile(sc.light.spot_exponent))
            ies.ies = txt
            em = next(n for n in nt.nodes if n.type == "EMISSION")
            nt.links.new(ies.outputs["Fac"], em.inputs["Strength"])

        # --- no world light: black background
        world = bpy.data.worlds.new("black")
        world.color = (0.0, 0.0, 0.0)
        if world.node_tree is None:  # Blender < 5 created node trees on request only
            world.use_nodes = True
        bg = world.node_tree.nodes.get("Background") if world.node_tree is not None else None
        if bg is not None:
            bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
            bg.inputs["Strength"].default_value = 0.0
        bs.world = world

        # --- Cycles
        r.engine = "CYCLES"
        c = bs.cycles
        c.device = "CPU"
        c.shading_system = self._per_point_texture()  # OSL: the appearance function per shading point
        c.samples = int(st.samples)
        c.use_adaptive_sampling = st.adaptive_threshold > 0
        if st.adaptive_threshold > 0:
            c.adaptive_threshold = float(st.adaptive_threshold)
            c.adaptive_min_samples = int(st.adaptive_min_samples)
        c.use_denoising = bool(st.denoise)
        if st.denoise:
            c.denoiser = "OPENIMAGEDENOISE"
            c.denoising_input_passes = "RGB_ALBEDO_NORMAL"
            c.denoising_prefilter = st.denoise_prefilter
            c.denoising_quality = st.denoise_quality
            c.denoising_use_gpu = False
        c.max_bounces = int(st.max_bounces)
        for k in ("diffuse_bounces", "glossy_bounces"):
            setattr(c, k, int(st.max_bounces))
        c.transmission_bounces = 0
        c.volume_bounces = 0
        c.transparent_max_bounces = 0
        c.caustics_reflective = c.caustics_refractive = False
        c.use_light_tree = False  # one light: nothing to choose between
        c.sample_clamp_direct = 0.0
        c.sample_clamp_indirect = float(st.clamp_indirect)
        c.blur_glossy = float(st.filter_glossy)
        c.seed = int(st.seed)
        c.use_animated_seed = False
        c.film_exposure = 1.0  # exposure is applied to the linear result (see exposure_ev)
        c.filter_width = float(st.filter_width)
        c.pixel_filter_type = "BLACKMAN_HARRIS"
        c.use_auto_tile = True
        c.tile_size = int(st.tile_size)
        r.use_motion_blur = False
        r.use_persistent_data = True
        r.film_transparent = False
        r.threads_mode = "FIXED" if st.threads else "AUTO"
        if st.threads:
            r.threads = int(st.threads)
        r.use_compositing = False
        r.use_sequencer = False
        r.dither_intensity = 0.0
        bs.view_settings.view_transform = "Standard"
        bs.view_settings.look = "None"

        vl = bs.view_layers[0]
        vl.use_pass_combined = True
        vl.use_pass_z = True
        vl.use_pass_normal = True
        vl.use_pass_vector = True

        im = r.image_settings
        im.media_type = "MULTI_LAYER_IMAGE"  # Blender 5.0: before the file format
        im.file_format = "OPEN_EXR_MULTILAYER"
        im.color_depth = "32"
        im.exr_codec = "NONE"
        im.use_exr_interleave = True  # one EXR part: Blender 5.0 fails writing multi-part EXRs with pixel aspect != 1
        r.use_file_extension = True

    def _material(self, bpy):
        m = self.scene.material
        mat = bpy.data.materials.new("mucosa")
        if mat.node_tree is None:  # Blender < 5 created node trees on request only
            mat.use_nodes = True
        nt = mat.node_tree
        bsdf = nt.nodes.get("Principled BSDF")
        if bsdf is None:
            bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
            out = nt.nodes.get("Material Output") or nt.nodes.new("ShaderNodeOutputMaterial")
            nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        bsdf.inputs["Base Color"].default_value = (*[float(x) for x in m.base_color], 1.0)
        if self._per_point_texture():  # Base Color <- the appearance function at the shading point (OSL)
            nt.links.new(self._osl_albedo(bpy, nt), bsdf.inputs["Base Color"])
        elif self.scene.vertex_albedo() is not None:  # textured: Base Color <- the per-vertex albedo attribute
            attr = nt.nodes.new("ShaderNodeAttribute")
            attr.attribute_type = "GEOMETRY"
            attr.attribute_name = ALBEDO_ATTRIBUTE
            nt.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
        bsdf.inputs["Roughness"].default_value = float(m.roughness)
        bsdf.inputs["Specular IOR Level"].default_value = float(m.specular)
        bsdf.inputs["Metallic"].default_value = 0.0
        bsdf.inputs["Subsurface Weight"].default_value = float(m.subsurface_weight)
        if m.subsurface_weight > 0:
            rad = np.asarray(m.subsurface_radius_m, dtype=np.float64)
            scale = float(rad.max())
            bsdf.inputs["Subsurface Radius"].default_value = tuple((rad / scale).tolist())
            bsdf.inputs["Subsurface Scale"].default_value = scale
            bsdf.subsurface_method = "RANDOM_WALK"
        return mat

    def _per_point_texture(self) -> bool:
        tex = self.scene.material.texture
        return self.settings.texture == "per_point" and tex is not None and tex.enabled

    def _osl_albedo(self, bpy, nt):
        sc = self.scene
        return osl_albedo_node(nt, sc.material.texture, sc.material.base_color, sc.vertex_airway is not None,
                               self.tmp_dir)

    @staticmethod
    def _set_camera(cam, pose_cv: np.ndarray) -> None:
        from mathutils import Matrix

        m = np.asarray(pose_cv, dtype=np.float64) @ CV_TO_BLENDER
        mw = Matrix([list(row) for row in m])
        loc, rot, _ = mw.decompose()
        cam.location = loc
        cam.rotation_quaternion = rot

    # --------------------------------------------------------------- exposure
    @property
    def exposure_ev(self) -> float:
        """EV applied to ``rgb``: the settings', else the Scene film's, else automatic-fixed (computed once)."""
        if self._exposure_ev is None:
            ev = self.settings.exposure
            film = getattr(self.scene, "film", None)
            if ev is None and film is not None:
                ev = film.exposure_ev
            if ev is None:
                ev = 0.0
                if film is not None:
                    from .shading import auto_exposure_ev

                    ref = min(max(int(film.auto_reference_frame), 0), len(self.scene.poses) - 1)
                    raw = self._render_raw(ref, ("rgb", "depth"))
                    ev = auto_exposure_ev(raw["rgb"], raw["depth"] > 0, film)
            self._exposure_ev = float(ev)
        return self._exposure_ev

    # ----------------------------------------------------------------- render
    def render(self, frame_index: int, modalities: Iterable[str] = MODALITIES) -> dict[str, np.ndarray | None]:
        """Render frame ``frame_index`` (pose ``scene.poses[frame_index]``); return the requested modalities.

        ``rgb`` is linear radiance x ``2**exposure_ev`` (the automatic exposure,
        when used, renders the reference frame once first).
        """
        mods = tuple(modalities)
        ev = self.exposure_ev if "rgb" in mods else 0.0
        out = self._render_raw(frame_index, mods)
        if out.get("rgb") is not None and ev != 0.0:
            out["rgb"] = (out["rgb"] * np.float32(2.0 ** ev)).astype(np.float32)
        return out

    def _render_raw(self, frame_index: int, modalities: Iterable[str]) -> dict[str, np.ndarray | None]:
        import time

        mods = tuple(modalities)
        bad = [m for m in mods if m not in MODALITIES]
        if bad:
            raise ConfigError(f"unknown modality {bad[0]!r} (known: {', '.join(MODALITIES)})")
        n = len(self.scene.poses)
        if not 0 <= frame_index < n:
            raise IndexError(f"frame {frame_index} out of range (0..{n - 1})")
        bpy = self._bpy
        bs = self._bscene
        vl = bs.view_layers[0]
        vl.use_pass_z = "depth" in mods
        vl.use_pass_normal = "normals" in mods
        vl.use_pass_vector = "flow" in mods and n > 1
        bs.frame_set(frame_index)
        path = self.tmp_dir / f"frame_{frame_index:06d}.exr"
        bs.render.filepath = str(path)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        self.last_render_s = time.perf_counter() - t0
        try:
            layers = _read_multilayer_exr(path)
        finally:
            if path.exists():
                path.unlink()
        self.notes = {}
        return self._convert(layers, frame_index, mods)

    def _convert(self, L: dict[str, np.ndarray], frame_index: int, mods: tuple[str, ...]) -> dict:
        out: dict[str, np.ndarray | None] = {}
        H, W = self.scene.camera.height, self.scene.camera.width
        depth = _get(L, "Depth", "Z")
        hit = None
        if depth is not None:
            d = depth[..., 0]
            hit = np.isfinite(d) & (d > 0) & (d < _NO_HIT_DEPTH)
        if "rgb" in mods:
            rgb = _get(L, "Combined", "RGB")
            out["rgb"] = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
        if "depth" in mods:
            out["depth"] = np.where(hit, depth[..., 0], 0.0).astype(np.float32)
        if "normals" in mods:
            n_world = _get(L, "Normal", "XYZ").astype(np.float64)
            R = self.scene.poses[frame_index][:3, :3]  # camera-to-world (OpenCV)
            n_cam = n_world @ R  # = (R^T n)^T row-wise
            ln = np.linalg.norm(n_cam, axis=-1, keepdims=True)
            ok = (ln[..., 0] > 1e-6) & np.isfinite(ln[..., 0])
            if hit is not None:
                ok &= hit
            n_cam = np.where(ok[..., None], n_cam / np.where(ln > 1e-6, ln, 1.0), 0.0)
            out["normals"] = np.nan_to_num(n_cam).astype(np.float32)
        if "flow" in mods:
            if frame_index + 1 >= len(self.scene.poses):
                out["flow"] = None
                self.notes["flow"] = "last frame: no pose t+1, forward flow undefined"
            else:
                vec = _get(L, "Vector", "XYZW")
                flow = np.stack([-vec[..., 2], vec[..., 3]], axis=-1)
                if hit is not None:
                    flow = np.where(hit[..., None], flow, 0.0)
                out["flow"] = np.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
        for k, a in out.items():
            if a is not None and a.shape[:2] != (H, W):
                raise RuntimeError(f"Cycles returned {k} of shape {a.shape}, expected {(H, W)}")
        return out

    # -------------------------------------------------------------- lifetime
    def close(self) -> None:
        if self._own_tmp:
            self._finalizer()

    def __enter__(self) -> "CyclesRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def osl_albedo_node(nt, tex, base_color, with_airway: bool, tmp_dir: Path):
    """An OSL script node in node tree ``nt`` evaluating the mucosa albedo (texture_osl.py); its output socket.

    Compiled with Cycles' built-in OSL compiler (source and bytecode written to
    ``tmp_dir``); the bytecode and its hash are stored on the node, and the
    sockets made here (Blender's own socket update needs the ``oslquery`` module,
    which the ``bpy`` wheel does not put on ``sys.path``).  With ``with_airway``
    the shader reads the airway coordinates from the mesh's POINT attributes
    (Attribute nodes).  Cycles must run OSL (``scene.cycles.shading_system``).
    """
    import hashlib

    import _cycles  # Cycles' Python module, loaded with bpy

    from .texture_osl import AIRWAY_GEN_ATTRIBUTE, AIRWAY_VECTOR_ATTRIBUTE, OUTPUT, SHADER_NAME, osl_source

    src, oso = Path(tmp_dir) / f"{SHADER_NAME}.osl", Path(tmp_dir) / f"{SHADER_NAME}.oso"
    src.write_text(osl_source(tex, tex.seed, base_color, with_airway), encoding="utf-8")
    if not _cycles.osl_compile(str(src), str(oso)):
        raise RuntimeError(f"Cycles could not compile the generated OSL shader {src}")
    code = oso.read_text(encoding="utf-8")
    node = nt.nodes.new("ShaderNodeScript")
    node.mode = "INTERNAL"
    node.bytecode = code
    node.bytecode_hash = hashlib.md5(code.encode(), usedforsecurity=False).hexdigest()
    node.outputs.new("NodeSocketColor", OUTPUT, identifier=OUTPUT)
    if with_airway:
        for name, sock, out in ((AIRWAY_VECTOR_ATTRIBUTE, "NodeSocketVector", "Vector"),
                                (AIRWAY_GEN_ATTRIBUTE, "NodeSocketFloat", "Fac")):
            node.inputs.new(sock, name, identifier=name)
            attr = nt.nodes.new("ShaderNodeAttribute")
            attr.attribute_type = "GEOMETRY"
            attr.attribute_name = name
            nt.links.new(attr.outputs[out], node.inputs[name])
    return node.outputs[OUTPUT]


def _add_airway_attributes(me, airway: np.ndarray) -> None:
    """The (V, 4) airway coordinates as the OSL shader's two POINT attributes of Blender mesh ``me``."""
    from .texture_osl import AIRWAY_GEN_ATTRIBUTE, AIRWAY_VECTOR_ATTRIBUTE

    air = np.asarray(airway, dtype=np.float32)
    me.attributes.new(AIRWAY_VECTOR_ATTRIBUTE, "FLOAT_VECTOR", "POINT").data.foreach_set(
        "vector", np.ascontiguousarray(air[:, :3]).ravel())
    me.attributes.new(AIRWAY_GEN_ATTRIBUTE, "FLOAT", "POINT").data.foreach_set("value", air[:, 3].copy())
    me.update()


def osl_albedo_at(points_world: np.ndarray, tex, base_color, airway: np.ndarray | None = None) -> np.ndarray:
    """Cycles' per-shading-point albedo (N, 3) float32 at world points (N, 3), metres: the OSL shader itself.

    Each point is the first vertex of its own triangle (20 nm sides), baked by
    Cycles (EMIT bake to a float colour attribute, 1 sample): what
    :class:`CyclesRenderer` with ``texture='per_point'`` shades there, for
    comparison with :func:`~room_pipeline.render.texture.mucosa_albedo`.
    ``airway``: optional (N, 4) coordinates.  Resets the process's Blender session.
    """
    bpy = import_bpy()

    p = np.asarray(points_world, dtype=np.float32).reshape(-1, 3)
    n = len(p)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bs = bpy.context.scene
    bs.render.engine = "CYCLES"
    bs.cycles.device = "CPU"
    bs.cycles.shading_system = True
    bs.cycles.samples = 1
    v = np.concatenate([p, p + np.float32([2e-8, 0, 0]), p + np.float32([0, 2e-8, 0])])
    me = bpy.data.meshes.new("probe")
    me.from_pydata(v.tolist(), [], (np.arange(3 * n).reshape(3, n).T).tolist())
    if airway is not None:
        _add_airway_attributes(me, np.tile(np.asarray(airway, dtype=np.float32).reshape(-1, 4), (3, 1)))
    out = me.color_attributes.new("baked", "FLOAT_COLOR", "CORNER")
    me.color_attributes.active_color = out
    obj = bpy.data.objects.new("probe", me)
    bs.collection.objects.link(obj)
    mat = bpy.data.materials.new("probe")
    if mat.node_tree is None:
        mat.use_nodes = True
    nt = mat.node_tree
    for nd in list(nt.nodes):
        nt.nodes.remove(nd)
    em = nt.nodes.new("ShaderNodeEmission")
    nt.links.new(em.outputs[0], nt.nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
    with tempfile.TemporaryDirectory(prefix="room_osl_") as d:
        nt.links.new(osl_albedo_node(nt, tex, base_color, airway is not None, Path(d)), em.inputs["Color"])
        me.materials.append(mat)
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
        bs.render.bake.target = "VERTEX_COLORS"
        bpy.ops.object.bake(type="EMIT")
    c = np.zeros(len(me.loops) * 4, dtype=np.float32)
    out.data.foreach_get("color", c)
    lv = np.zeros(len(me.loops), dtype=np.int64)
    me.loops.foreach_get("vertex_index", lv)
    res = np.zeros((n, 3), dtype=np.float32)
    first = lv < n
    res[lv[first]] = c.reshape(-1, 4)[first, :3]
    return res


def _fcurves(action):
    """F-curves of an action (Blender 5.0 moved them into layered channelbags)."""
    if hasattr(action, "fcurves"):
        try:
            return list(action.fcurves)
        except Exception:  # pragma: no cover - layered actions
            pass
    curves = []
    for layer in getattr(action, "layers", []):
        for strip in layer.strips:
            for bag in getattr(strip, "channelbags", []):
                curves.extend(bag.fcurves)
    return curves


def _read_multilayer_exr(path: Path) -> dict[str, np.ndarray]:
    """Multilayer EXR -> {channel name: (H, W) float32}, rows top to bottom (OpenImageIO).

    Blender 5.0 writes one EXR *part* (OpenImageIO subimage) per pass, so every
    subimage is read.
    """
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"cannot open {path}: {oiio.geterror()}")
    out: dict[str, np.ndarray] = {}
    try:
        sub = 0
        while inp.seek_subimage(sub, 0):
            spec = inp.spec()
            data = inp.read_image(sub, 0, 0, spec.nchannels, "float")
            if data is None:
                raise RuntimeError(f"cannot read {path} part {sub}: {inp.geterror()}")
            data = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
            for i, name in enumerate(spec.channelnames):
                out[name] = data[..., i]
            sub += 1
    finally:
        inp.close()
    return out


def _get(L: dict[str, np.ndarray], layer: str, chans: str) -> np.ndarray | None:
    """Stack channels ``<ViewLayer>.<layer>.<c>`` for c in ``chans`` -> (H, W, len(chans)), or None."""
    out = []
    for c in chans:
        key = next((k for k in L if k.endswith(f".{layer}.{c}") or k == f"{layer}.{c}"), None)
        if key is None:
            return None
        out.append(L[key])
    return np.stack(out, axis=-1)
