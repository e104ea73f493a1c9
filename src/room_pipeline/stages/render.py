"""Stage `render`: a sequence's camera poses + the lumen mesh -> the ROOM modalities.

Writes into ``<patient>/<sequence>/``: ``rgb/frame_NNNN.png`` (8-bit sRGB),
``depth/frame_NNNN.exr`` (planar z, float32 metres rounded to 2^-17 m, channel Y, 0 = no hit),
``relative_depth/frame_NNNN.png`` (16-bit normalised inverse depth, 0 = no hit;
per-frame [d_min, d_max] in ``metadata/render.json``),
``surface_normals/frame_NNNN.exr`` (half-float unit normals in the OpenCV camera
frame, facing the camera; channels R, G, B = x, y, z; 0 = no hit),
``optical_flow/frame_NNNN.exr`` (half float, R, G = u, v; or Middlebury ``.flo``
with ``render.storage.flow_format=flo``; forward t -> t+1, pixels) with
``optical_flow/valid_NNNN.png`` (255 = valid: visible at t+1, inside, not
occluded), ``point_clouds/`` (``point_clouds.json``, and with
``render.storage.point_clouds=ply`` a binary PLY per frame: camera frame,
metres, normals, colour; by default generated on demand by the reader),
``segmentation/frame_NNNN.png`` (uint16: airway branch id + 1, 0 =
no hit) with ``segmentation/legend.json`` (label -> branch id, generation),
``calibration/camera_params.json`` and ``metadata/render.json`` (renderer,
exposure, per-frame source index, timestamp, camera-to-world pose).  Precision,
codec and error bound of every modality (``render.storage``,
:mod:`room_pipeline.io.storage`) are stated in both JSON files ("storage").

Execution (config section ``execution``, :mod:`room_pipeline.execution`):
the frames of the sequence fan out over the executor's workers (serial, local
processes or Ray actors), each building its renderers once
(:func:`_frame_worker`) and rendering contiguous blocks of frame indices
(:func:`_render_block`; :func:`_render_frame` hands the frame's files to the
worker's :class:`~room_pipeline.io.storage.FrameWriter`, whose threads encode
and write them atomically while the next frame is cast; a block returns its
records once all its files are on disk).  Everything computed once per sequence is computed here, before the
fan-out: face labels, the vertices' airway coordinates, the automatic
exposure (by default the ray caster's per-frame exposures from a sequential
meter pre-pass, :mod:`room_pipeline.render.exposure`; with backend
``cycles``, Cycles' own EV on the film's reference frame) and the renderer
metadata; the workers get the exposures fixed.  So the backend and the
number of workers change no byte of the outputs.
"""
from __future__ import annotations

import dataclasses
import os
import resource
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from omegaconf import DictConfig
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph
from ..config.compose import section
from ..config.params import params_from_dict
from ..conventions import MM, metadata_block
from ..errors import ConfigError, InputError
from ..execution import ExecutionParams, ensure_writable, make_executor, remove_stale_temp_files
from ..io.atomic import write_json
from ..io.images import write_png8, write_png16
from ..io.storage import POINT_CLOUD_JSON, FrameWriter, StorageParams, stride_mask
from ..io.mesh import Mesh, read_obj
from ..io.records import pose_track
from ..render.camera import CameraIntrinsics
from ..render.scene import Film, Scene, TipLight, TissueMaterial
from ..render.texture import MucosaTexture, airway_coordinates
from .common import StageTimer, metadata, patient_paths, read_json, write_metrics
from ..catalog import RENDER_FOLDERS as FOLDERS, SequencePaths, split_key  # FOLDERS: modality -> folder


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
    base_color: tuple = (0.95, 0.392, 0.454)
    roughness: float = 0.35
    specular: float = 0.5
    interreflection: float = 0.0
    interreflection_window_mm: float = 6.0
    indirect_bounces: int = 0
    indirect_rays_per_point: int = 64
    indirect_seed: int = 0
    indirect_shadows: bool = True
    light_power_w: float = 0.02
    light_radius_mm: float = 0.5
    light_offset_mm: tuple = (0.0, -1.1, 0.0)
    light_spot_exponent: float = 2.767
    light_falloff: str = "inverse_square"
    light_falloff_length_mm: float = 20.0
    exposure_ev: float | None = None
    auto_exposure: str = "per_frame"
    auto_exposure_target: float = 0.5
    auto_exposure_percentile: float = 95.0
    auto_exposure_smoothing_s: float = 0.3
    auto_exposure_min_ev: float = -12.0
    auto_exposure_max_ev: float = 12.0
    auto_exposure_highlight_percentile: float = 99.0
    auto_exposure_highlight_max: float = 0.9
    vignetting: float = 0.0
    veiling_glare: float = 0.12
    response: str = "srgb"
    gamma: float = 2.2
    shading_stride: int = 2
    texture: dict = dataclasses.field(default_factory=dict)
    cycles_samples: int = 4
    cycles_denoise: bool = True
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
    from ..render.exposure import ExposureParams

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
    from ..render.indirect import IndirectConfig

    return IndirectConfig(bounces=p.indirect_bounces, rays_per_point=p.indirect_rays_per_point,
                          seed=p.indirect_seed, shadows=p.indirect_shadows)


def raycast_config(p: "RenderParams", nthreads: int = 0):
    """The ray caster's configuration of the render config."""
    from ..render.raycast import RaycastConfig

    return RaycastConfig(nthreads=nthreads, shading_stride=p.shading_stride, indirect=indirect_config(p))


def texture_params(d: Mapping[str, Any] | None) -> MucosaTexture:
    """The ``render.texture`` section as a :class:`MucosaTexture` (unknown key or bad value: ConfigError)."""
    if d is not None and not isinstance(d, Mapping):
        raise ConfigError(f"render.texture must be a mapping, got {d!r}")
    try:
        return params_from_dict(MucosaTexture, d, "render.texture")
    except ValueError as e:
        raise ConfigError(str(e).splitlines()[0]) from None


def outputs(cfg: DictConfig, key: str) -> list:
    patient, sequence = split_key(key)
    seq = patient_paths(cfg, patient).seq(sequence)
    return seq.render_folders() + [seq.calibration, seq.render_json]


def face_labels(mesh: Mesh, graph: CentrelineGraph) -> tuple[np.ndarray, dict]:
    """Per-face airway branch id (nearest centreline point to the face centroid) and the legend."""
    pts, _, bid = graph.all_points()
    if len(pts) == 0:
        return np.zeros(mesh.n_faces, np.int32), {}
    _, idx = cKDTree(pts).query(mesh.vertices[mesh.faces].mean(axis=1))
    labels = bid[idx].astype(np.int32)
    legend = {str(b.id + 1): {"branch_id": b.id, "generation": b.generation, "parent": b.parent}
              for b in graph.branches}
    return labels, legend


def load_poses(meta_dir, which: str) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, camera-to-world poses) of the planned or the simulated sequence."""
    sp = SequencePaths(Path(meta_dir).parent)
    path = sp.simulation if which == "simulated" else sp.trajectory
    track = pose_track(path, read_json(path))
    return track.timestamps, track.poses


def execution_params(cfg: DictConfig, frames: int | None = None) -> ExecutionParams:
    """The ``execution`` section (defaults when absent; ``workers: 0`` resolved for ``frames`` frames:
    :meth:`ExecutionParams.resolved`); ``local`` with one worker runs in this process.

    One spawned process would only add its start-up time: the frames are the
    same bytes either way.  Several processes are what uses several cores:
    Open3D's ``cast_rays`` holds the GIL, so threads of one process cannot
    cast and encode at once (``benchmarks/results/write_throughput.md``).
    """
    p = ExecutionParams.from_dict(section(cfg, "execution") if "execution" in cfg else None).resolved(frames)
    if p.backend == "local" and p.workers == 1:
        return dataclasses.replace(p, backend="serial")
    return p


def _cycles_settings(p: RenderParams, **kw: Any):
    from ..render.blender import CyclesSettings

    return CyclesSettings.from_dict({"samples": p.cycles_samples, "denoise": p.cycles_denoise, **kw})


class _Renderers:
    """The fast ray caster for every geometric modality; with backend 'cycles' the RGB comes from Cycles.

    The product writes geometric depth, normals and flow in both cases: Cycles' passes agree with them
    (depth 2e-5 relative, flow 0.007 px; tests/test_blender.py) but its vector pass blends the two
    surfaces at silhouettes, where the geometric flow is exact.  ``nthreads``: Open3D casting threads
    (0 = all cores); ``cycles_ev`` (stops) and ``cycles_threads`` (0 = all cores) for Cycles.
    """

    def __init__(self, scene: Scene, p: RenderParams, nthreads: int = 0, cycles_ev: float | None = None,
                 cycles_threads: int = 0) -> None:
        from ..render.raycast import RaycastRenderer

        self.raycast = RaycastRenderer(scene, raycast_config(p, nthreads))
        self.cycles = None
        if p.backend == "cycles":
            from ..render.blender import CyclesRenderer

            self.cycles = CyclesRenderer(scene, _cycles_settings(p, exposure=cycles_ev, threads=cycles_threads))

    def render(self, i: int, mods: set) -> dict:
        if self.cycles is None:
            return self.raycast.render(i, mods)
        from ..render.blender import linear_to_srgb8

        out = self.raycast.render(i, mods - {"rgb"})
        if "rgb" in mods:
            lin = self.cycles.render(i, ("rgb",))["rgb"]
            film = self.raycast.scene.film
            if film.frame_ev is None and film.vignetting == 0 and film.response == "srgb" and not film.veiling_glare:
                out["rgb"] = linear_to_srgb8(lin)
            else:        # the per-frame exposure, vignetting and response, as the ray caster applies them
                from ..render.shading import apply_response

                lin = lin * np.float32(2.0 ** (film.ev(i, 0.0) - self.cycles.exposure_ev)) if film.frame_ev else lin
                if film.vignetting > 0:
                    lin = lin * (self.raycast._inv_ray_len ** np.float32(film.vignetting))[..., None]
                out["rgb"] = apply_response(lin, film)
            if "point_cloud" in out:
                out["point_cloud_colors"] = out["rgb"][out["hit"]]
        return out

    def close(self) -> None:
        if self.cycles is not None:
            self.cycles.close()


def _exposure_once(scene: Scene, p: RenderParams) -> tuple[dict, float, float | None]:
    """What is computed once per sequence, in the driver: (renderer metadata, ray-caster EV, Cycles EV, per-frame EVs).

    With ``render.auto_exposure: per_frame`` (and no fixed ``exposure_ev``) the
    ray caster's per-frame exposures come from a sequential meter pre-pass
    here, before the fan-out (:mod:`room_pipeline.render.exposure`), so they
    do not depend on the executor; Cycles keeps one EV per sequence.

    Both automatic exposures are chosen on the film's reference frame by the
    renderer that uses them (Cycles renders that frame once here, with the film
    as configured); the metadata is the ray caster's with its default config.
    """
    from ..render.raycast import RaycastRenderer

    cycles_ev, settings = None, None
    if p.backend == "cycles":
        from ..render.blender import CyclesRenderer

        settings = _cycles_settings(p)
        with CyclesRenderer(scene, settings) as cy:
            cycles_ev = cy.exposure_ev
    frame_ev = None
    if p.exposure_ev is None and p.auto_exposure == "per_frame":
        from ..render.exposure import exposure_track

        frame_ev = exposure_track(scene, exposure_params(p), indirect=indirect_config(p))
        scene = dataclasses.replace(scene, film=dataclasses.replace(scene.film, frame_ev=frame_ev))
    probe = RaycastRenderer(scene, raycast_config(p))
    meta = probe.metadata()                      # computes the automatic EV (one cast of the reference frame)
    ev = probe.exposure_ev
    if frame_ev is not None:
        meta["auto_exposure"] = {"mode": "per_frame", "params": dataclasses.asdict(exposure_params(p)),
                                 "frame_ev": list(frame_ev),
                                 "method": "room_pipeline.render.exposure: low-resolution meter pass, percentile "
                                           "luminance -> target, causal exponential smoothing in EV, clamped"}
    if settings is not None:
        meta = {"rgb": {"backend": "blender_cycles", "exposure_ev": cycles_ev,
                        "settings": dataclasses.asdict(settings)},
                "geometry": meta}
    return meta, ev, cycles_ev, frame_ev


def _drop_inherited_bpy_paths() -> None:
    """Let ``import bpy`` work in a worker spawned by a process that had imported bpy.

    Importing bpy puts Blender's script folders (``.../site-packages/bpy/<ver>/scripts/...``) on
    ``sys.path``; a spawned process inherits that ``sys.path``, so its ``import bpy`` would find
    Blender's inner ``bpy`` package (which needs the ``_bpy`` built-in) instead of the bpy module.
    Until bpy is imported here, those folders are dropped.
    """
    if "bpy" not in sys.modules:
        marker = f"{os.sep}site-packages{os.sep}bpy{os.sep}"
        sys.path[:] = [d for d in sys.path if marker not in d]


def _frame_worker(scene: Scene, p: RenderParams, seq: str, src: np.ndarray, ts: np.ndarray, poses: np.ndarray,
                  nthreads: int, cycles_ev: float | None, cycles_threads: int) -> dict:
    """Per-worker state, built once: the renderers (BVH, Blender scene) and what names and records a frame."""
    if p.backend == "cycles":
        _drop_inherited_bpy_paths()
    r = _Renderers(scene, p, nthreads=nthreads, cycles_ev=cycles_ev, cycles_threads=cycles_threads)
    if r.cycles is not None:     # spawned workers end without running weakref finalizers: remove Cycles' temp dir
        import multiprocessing.util

        multiprocessing.util.Finalize(r, r.cycles.close, exitpriority=10)
    st = StorageParams.from_dict(p.storage)
    mods = set(p.modalities)
    if "point_cloud" in mods and st.point_clouds == "on_demand":
        mods.discard("point_cloud")                 # built by the reader from depth / normals / rgb
    return {"r": r, "seq": Path(seq), "mods": mods, "src": src, "ts": ts, "poses": poses, "storage": st,
            "writer": FrameWriter(st.write_threads, st.max_pending)}


def _render_block(state: dict, block: tuple[int, int]) -> list[dict]:
    """Render frames ``block[0] .. block[1] - 1`` in order; return their records once all their files are written."""
    writer: FrameWriter = state["writer"]
    out = []
    try:
        for i in range(*block):
            out.append(_render_frame(state, i))
    finally:
        writer.wait()
    return out


def _render_frame(state: dict, i: int) -> dict:
    """Render frame ``i``, hand its files to the writer (atomic writes) and return its record and summary numbers.

    Every array handed over is one the renderer will not touch again: fresh
    arrays per frame, and the cached cast's depth, which nothing writes to
    (``StorageParams.write_depth`` rounds a copy, on the writer thread).
    """
    seq, src, ts, poses = state["seq"], state["src"], state["ts"], state["poses"]
    st: StorageParams = state["storage"]
    put = state["writer"].submit
    out = state["r"].render(i, state["mods"])
    name = f"frame_{i:04d}"
    hit = out["hit"]
    rec = {"index": i, "source_index": int(src[i]), "timestamp": float(ts[src[i]]),
           "pose": np.round(poses[src[i]], 12).tolist(), "hit_fraction": float(hit.mean())}
    flow_valid = None
    # conversions (depth rounding, label + 1, mask to 8 bits, half floats) run on the writer threads too
    if "rgb" in out:
        put(write_png8, seq / "rgb" / f"{name}.png", out["rgb"], int(st.png_level))
    if "depth" in out:
        put(st.write_depth, seq / "depth" / f"{name}.exr", out["depth"], hit)
    if "relative_depth" in out:
        put(write_png16, seq / "relative_depth" / f"{name}.png", out["relative_depth"], int(st.png_level))
        rec["relative_depth_range_m"] = [float(x) for x in out["relative_depth_range"]]
    if "normals" in out:
        put(st.write_normals, seq / "surface_normals" / f"{name}.exr", out["normals"])
    if "flow" in out:
        put(st.write_flow, seq / "optical_flow" / f"{name}{st.flow_ext}", out["flow"])
        put(st.write_flow_valid, seq / "optical_flow" / f"valid_{i:04d}.png", out["flow_valid"])
        flow_valid = float(out["flow_valid"].mean())
    if "point_cloud" in out:
        from ..render.raycast import write_point_cloud

        if st.point_cloud_stride > 1:
            keep = stride_mask(hit, st.point_cloud_stride)[hit]
            out = {k: (v[keep] if k.startswith("point_cloud") else v) for k, v in out.items()}
        put(write_point_cloud, seq / "point_clouds" / f"{name}.ply", out, i, poses[src[i]])
    if "segmentation" in out:
        put(st.write_segmentation, seq / "segmentation" / f"{name}.png", out["segmentation"])
    return {"rec": rec, "hit": float(hit.mean()), "flow_valid": flow_valid, "pid": os.getpid(),
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def frame_blocks(n: int, size: int) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` blocks of at most ``size`` frames covering ``range(n)``."""
    return [(s, min(s + size, n)) for s in range(0, n, max(1, int(size)))]


def _peak_rss_mb(results: list[dict]) -> float:
    """Peak resident memory (MB): this process plus each worker process's high-water mark.

    The workers report their own ``ru_maxrss`` with every frame (local processes
    and Ray actors alike); ``RUSAGE_CHILDREN`` covers children that ended
    without reporting (it holds the largest one only).  Peaks of different
    processes need not coincide, so this is an upper bound of the total.
    """
    me = os.getpid()
    workers: dict[int, float] = {}
    for r in results:
        if r["pid"] != me:
            workers[r["pid"]] = max(workers.get(r["pid"], 0.0), r["rss_mb"])
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return own + max(sum(workers.values()), children)


def run(cfg: DictConfig, key: str) -> dict:
    patient, sequence = split_key(key)
    p = RenderParams.from_dict(section(cfg, "render"))
    storage = StorageParams.from_dict(p.storage)
    execution_params(cfg)                                   # bad execution config: stop before any work
    paths = patient_paths(cfg, patient)
    seq = paths.sequence(sequence)
    sp = paths.seq(sequence)
    with StageTimer() as timer:
        ts, poses = load_poses(paths.sequence_metadata(sequence), p.poses)
        src = np.arange(0, len(ts), p.frame_stride)
        if p.max_frames is not None:
            src = src[: int(p.max_frames)]
        if len(src) == 0:
            raise InputError(f"{sequence}: no poses to render")
        ex_params = execution_params(cfg, len(src))
        parallel = ex_params.backend != "serial" and ex_params.workers > 1
        mods = set(p.modalities)
        ensure_writable(*sp.render_folders(), sp.calibration, sp.metadata)
        remove_stale_temp_files(seq)
        mesh = read_obj(paths.mesh)
        graph = CentrelineGraph.from_dict(read_json(paths.centreline_graph))
        labels, legend = face_labels(mesh, graph)
        cam = camera_of(p)
        material, light, film = scene_parts(p)
        airway = airway_coordinates(mesh.vertices, graph) if material.texture.enabled else None
        scene = Scene(mesh, cam, poses[src], ts[src], material=material, light=light, film=film,
                      face_labels=labels, vertex_airway=airway)
        renderer_meta, ev, cycles_ev, frame_ev = _exposure_once(scene, p)
        # every worker: the same exposures (fixed EV, or the per-frame track of the driver's meter pass)
        scene.film = dataclasses.replace(scene.film, exposure_ev=ev, frame_ev=frame_ev)
        # each worker's Open3D casts and Cycles get the executor's per-worker thread budget (0: all cores)
        nthreads = ex_params.threads if parallel else 0
        cycles_threads = ex_params.threads if parallel else 0
        init = (_frame_worker, (scene, p, str(seq), src, ts, poses, nthreads, cycles_ev, cycles_threads))
        with make_executor(ex_params, init=init) as ex:
            # blocks small enough that every worker gets several (the executor hands out contiguous chunks of them)
            block = storage.write_block if not parallel else \
                max(1, min(storage.write_block, -(-len(src) // (4 * ex_params.workers))))
            blocks = ex.map(_render_block, frame_blocks(len(src), block), desc=f"render {key} (blocks of {block} frames)")
        results = [r for b in blocks for r in b]
        frames = [r["rec"] for r in results]
        n_hit = [r["hit"] for r in results]
        n_valid_flow = [r["flow_valid"] for r in results if r["flow_valid"] is not None]
    if "segmentation" in mods:
        write_json(sp.legend,
                   {"encoding": "uint16 PNG: label = airway branch id + 1, 0 = no hit",
                    "branch_ids": "centreline_graph.json ids", "labels": legend})
    # without point_cloud in render.modalities no PLY is written: the reader builds clouds from depth/ then
    stored = storage if "point_cloud" in mods else dataclasses.replace(storage, point_clouds="on_demand")
    precision = stored.precision()
    write_json(sp.folder("point_cloud") / POINT_CLOUD_JSON, {**precision["point_clouds"], "requested": "point_cloud" in mods})
    write_json(sp.camera, {**cam.to_dict(), "storage": precision})
    write_json(sp.render_json, {
        "renderer": renderer_meta, "storage": {"params": dataclasses.asdict(storage), "precision": precision},
        "poses": p.poses, "modalities": sorted(mods), "frames": frames,
        "flow": "forward t -> t+1 in pixels (u right, v down); the last frame has zero flow and no valid pixel",
        "conventions": metadata_block(),
        "metadata": metadata("render", patient, cfg, ("render",), sequence=sequence)})
    metrics = {"frames": len(frames), "hit_fraction_mean": round(float(np.mean(n_hit)), 6),
               "flow_valid_fraction_mean": round(float(np.mean(n_valid_flow)), 6) if n_valid_flow else None,
               "wall_time_s": round(timer.wall_s, 3), "frames_per_s": round(len(frames) / timer.wall_s, 3),
               "peak_rss_mb": round(_peak_rss_mb(results), 1), "workers": ex_params.workers}
    if "rgb" in mods:       # realism metrics of the clean RGB (room_pipeline.realism; real-frame distances: room realism)
        from ..realism import sequence_metrics

        metrics.update(sequence_metrics(sorted((seq / "rgb").glob("frame_*.png"))))
        if frame_ev is not None:
            metrics["exposure_ev_min"], metrics["exposure_ev_max"] = min(frame_ev), max(frame_ev)
    write_metrics(paths, f"render_{sequence}", metrics)
    return metrics
