"""Rendering one sequence: the ROOM modalities of a sequence's camera poses in the lumen mesh.

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
(:func:`frame_worker`) and rendering contiguous blocks of frame indices
(:func:`render_block`; :func:`render_frame` hands the frame's files to the
worker's :class:`~room_pipeline.io.storage.FrameWriter`, whose threads encode
and write them atomically while the next frame is cast; a block returns its
records once all its files are on disk).  Everything computed once per sequence is computed here, before the
fan-out: face labels, the vertices' airway coordinates, the automatic-fixed
exposure (the ray caster's on the film's reference frame, which also builds the inter-reflection's gather
matrix the workers adopt; with backend ``cycles``, Cycles' own EV) and the renderer metadata.  The per-frame
exposures (``render.auto_exposure: per_frame``, the default) are metered first on the same workers, a frame
each (:func:`meter_block`, :mod:`room_pipeline.render.exposure`), and smoothed in time here in frame order; every
render block then carries the whole track.  So the backend and the number of workers change no byte of the
outputs.
"""
from __future__ import annotations

import dataclasses
import os
import resource
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig
from scipy.spatial import cKDTree

from ..anatomy.centreline import CentrelineGraph
from ..catalog import RENDER_FOLDERS, SequencePaths
from ..config.compose import section
from ..conventions import metadata_block
from ..errors import InputError
from ..execution import ExecutionParams, make_executor, params_for_items
from ..io.images import write_png8, write_png16
from ..io.jsondoc import read_json
from ..io.mesh import Mesh
from ..io.records import pose_track
from ..io.storage import FrameWriter, StorageParams, stride_mask
from .params import (RenderParams, camera_of, cycles_settings, exposure_params, indirect_config, raycast_config,
                     scene_parts)
from .scene import Scene
from .texture import airway_coordinates


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
    """The ``execution`` section for ``frames`` frames (:func:`room_pipeline.execution.params_for_items`:
    defaults when absent, ``workers: 0`` resolved, ``local`` with one worker in this process).

    Several processes are what uses several cores: Open3D's ``cast_rays`` holds the GIL, so threads of one
    process cannot cast and encode at once (``benchmarks/results/write_throughput.md``).
    """
    return params_for_items(section(cfg, "execution") if "execution" in cfg else None, frames)


class Renderers:
    """The fast ray caster for every geometric modality; with backend 'cycles' the RGB comes from Cycles.

    The product writes geometric depth, normals and flow in both cases: Cycles' passes agree with them
    (depth 2e-5 relative, flow 0.007 px; tests/test_blender.py) but its vector pass blends the two
    surfaces at silhouettes, where the geometric flow is exact.  ``nthreads``: Open3D casting threads
    (0 = all cores); ``cycles_ev`` (stops) and ``cycles_threads`` (0 = all cores) for Cycles.
    """

    def __init__(self, scene: Scene, p: RenderParams, nthreads: int = 0, cycles_ev: float | None = None,
                 cycles_threads: int = 0) -> None:
        from .raycast import RaycastRenderer

        self.raycast = RaycastRenderer(scene, raycast_config(p, nthreads))
        self.cycles = None
        if p.backend == "cycles":
            from .blender import CyclesRenderer

            self.cycles = CyclesRenderer(scene, cycles_settings(p, exposure=cycles_ev, threads=cycles_threads))

    def render(self, i: int, mods: set) -> dict:
        if self.cycles is None:
            return self.raycast.render(i, mods)
        from .blender import linear_to_srgb8

        out = self.raycast.render(i, mods - {"rgb"})
        if "rgb" in mods:
            lin = self.cycles.render(i, ("rgb",))["rgb"]
            film = self.raycast.scene.film
            if film.frame_ev is None and film.vignetting == 0 and film.response == "srgb" and not film.veiling_glare:
                out["rgb"] = linear_to_srgb8(lin)
            else:        # the per-frame exposure, vignetting and response, as the ray caster applies them
                from .shading import apply_response

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


def exposure_probe(scene: Scene, p: RenderParams):
    """What is computed once per sequence in the driver before the fan-out: ``(probe, ray-caster EV, Cycles EV,
    Cycles settings)``.  ``probe``: the ray caster with its default config on ``scene``, whose automatic EV (one
    cast of the film's reference frame) also builds the inter-reflection's gather matrix the workers adopt.

    Both automatic exposures are chosen on the film's reference frame by the renderer that uses them (Cycles
    renders that frame once here, with the film as configured); with ``render.auto_exposure: per_frame`` the ray
    caster's per-frame exposures come on top (:func:`meter_block` on the workers, then
    :func:`~room_pipeline.render.exposure.smooth_exposures` here); Cycles keeps one EV per sequence.
    """
    from .raycast import RaycastRenderer

    cycles_ev, settings = None, None
    if p.backend == "cycles":
        from .blender import CyclesRenderer

        settings = cycles_settings(p)
        with CyclesRenderer(scene, settings) as cy:
            cycles_ev = cy.exposure_ev
    probe = RaycastRenderer(scene, raycast_config(p))
    return probe, probe.exposure_ev, cycles_ev, settings


def per_frame_exposure(p: RenderParams) -> bool:
    """The scope's gain control: ``render.auto_exposure: per_frame`` and no fixed ``exposure_ev``."""
    return p.exposure_ev is None and p.auto_exposure == "per_frame"


def renderer_metadata(probe, film, p: RenderParams, frame_ev: tuple | None, settings,
                      cycles_ev: float | None) -> dict:
    """``render.json``'s ``renderer``: the probe's metadata with ``film`` (as configured) and the per-frame
    exposures, the meter's parameters and method; under ``geometry``, beside Cycles' RGB settings, for backend
    ``cycles``."""
    meta = probe.metadata()
    meta["film"] = dataclasses.asdict(dataclasses.replace(film, frame_ev=frame_ev))
    if frame_ev is not None:
        meta["auto_exposure"] = {"mode": "per_frame", "params": dataclasses.asdict(exposure_params(p)),
                                 "frame_ev": list(frame_ev),
                                 "method": "room_pipeline.render.exposure: low-resolution meter pass, percentile "
                                           "luminance -> target, causal exponential smoothing in EV, clamped"}
    if settings is not None:
        meta = {"rgb": {"backend": "blender_cycles", "exposure_ev": cycles_ev,
                        "settings": dataclasses.asdict(settings)},
                "geometry": meta}
    return meta


def frame_worker(scene: Scene, p: RenderParams, seq: str, src: np.ndarray, ts: np.ndarray, poses: np.ndarray,
                  nthreads: int, cycles_ev: float | None, cycles_threads: int, gather: dict | None = None) -> dict:
    """Per-worker state, built once: the renderers (BVH, Blender scene) and what names and records a frame.
    ``gather``: the driver's inter-reflection gather matrices (:func:`~room_pipeline.render.indirect.gather_cache`;
    the same mesh and knobs give the same bytes, so a worker takes them instead of casting the rays again)."""
    if gather:
        from .indirect import adopt_gather_cache

        adopt_gather_cache(gather)
    r = Renderers(scene, p, nthreads=nthreads, cycles_ev=cycles_ev, cycles_threads=cycles_threads)
    if r.cycles is not None:     # spawned workers end without running weakref finalizers: remove Cycles' temp dir
        import multiprocessing.util

        multiprocessing.util.Finalize(r, r.cycles.close, exitpriority=10)
    st = StorageParams.from_dict(p.storage)
    mods = set(p.modalities)
    if "point_cloud" in mods and st.point_clouds == "on_demand":
        mods.discard("point_cloud")                 # built by the reader from depth / normals / rgb
    sp = SequencePaths(Path(seq))
    return {"r": r, "seq": sp.root, "folders": {m: sp.folder(m) for m in RENDER_FOLDERS}, "mods": mods,
            "src": src, "ts": ts, "poses": poses, "storage": st,
            "writer": FrameWriter(st.write_threads, st.max_pending),
            "scene": scene, "params": p, "nthreads": nthreads, "meter": None}


def meter_block(state: dict, block: tuple[int, int]) -> list[tuple[float, float]]:
    """The exposure meter's raw exposure and highlight limit (EV) of frames ``block[0] .. block[1] - 1``
    (:class:`~room_pipeline.render.exposure.ExposureMeter`, built on the worker's first block)."""
    if state["meter"] is None:
        from .exposure import ExposureMeter

        p = state["params"]
        state["meter"] = ExposureMeter(state["scene"], exposure_params(p), state["nthreads"], indirect_config(p))
    return [state["meter"].frame(i) for i in range(*block)]


def render_block(state: dict, block: tuple) -> list[dict]:
    """Render frames ``block[0] .. block[1] - 1`` in order; return their records once all their files are written.
    ``block[2]``, when given: the sequence's per-frame exposures (EV), set on the worker's film first."""
    if len(block) > 2 and block[2] is not None:
        scene = state["r"].raycast.scene
        if scene.film.frame_ev != block[2]:
            scene.film = dataclasses.replace(scene.film, frame_ev=tuple(block[2]))
    writer: FrameWriter = state["writer"]
    out = []
    try:
        for i in range(block[0], block[1]):
            out.append(render_frame(state, i))
    finally:
        writer.wait()
    return out


def render_frame(state: dict, i: int) -> dict:
    """Render frame ``i``, hand its files to the writer (atomic writes) and return its record and summary numbers.

    Every array handed over is one the renderer will not touch again: fresh
    arrays per frame, and the cached cast's depth, which nothing writes to
    (``StorageParams.write_depth`` rounds a copy, on the writer thread).
    """
    src, ts, poses = state["src"], state["ts"], state["poses"]
    dirs = state["folders"]
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
        put(write_png8, dirs["rgb"] / f"{name}.png", out["rgb"], int(st.png_level))
    if "depth" in out:
        put(st.write_depth, dirs["depth"] / f"{name}.exr", out["depth"], hit)
    if "relative_depth" in out:
        put(write_png16, dirs["relative_depth"] / f"{name}.png", out["relative_depth"], int(st.png_level))
        rec["relative_depth_range_m"] = [float(x) for x in out["relative_depth_range"]]
    if "normals" in out:
        put(st.write_normals, dirs["normals"] / f"{name}.exr", out["normals"])
    if "flow" in out:
        put(st.write_flow, dirs["flow"] / f"{name}{st.flow_ext}", out["flow"])
        put(st.write_flow_valid, dirs["flow"] / f"valid_{i:04d}.png", out["flow_valid"])
        flow_valid = float(out["flow_valid"].mean())
    if "point_cloud" in out:
        from .raycast import write_point_cloud

        if st.point_cloud_stride > 1:
            keep = stride_mask(hit, st.point_cloud_stride)[hit]
            out = {k: (v[keep] if k.startswith("point_cloud") else v) for k, v in out.items()}
        put(write_point_cloud, dirs["point_cloud"] / f"{name}.ply", out, i, poses[src[i]])
    if "segmentation" in out:
        put(st.write_segmentation, dirs["segmentation"] / f"{name}.png", out["segmentation"])
    return {"rec": rec, "hit": float(hit.mean()), "flow_valid": flow_valid, "pid": os.getpid(),
            "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def frame_blocks(n: int, size: int) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` blocks of at most ``size`` frames covering ``range(n)``."""
    return [(s, min(s + size, n)) for s in range(0, n, max(1, int(size)))]


def peak_rss_mb(results: list[dict]) -> float:
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


def select_frames(n_poses: int, p: RenderParams, sequence: str) -> np.ndarray:
    """Source pose indices rendered: every ``frame_stride``-th, at most ``max_frames``; none: InputError."""
    src = np.arange(0, n_poses, p.frame_stride)
    if p.max_frames is not None:
        src = src[: int(p.max_frames)]
    if len(src) == 0:
        raise InputError(f"{sequence}: no poses to render")
    return src


@dataclasses.dataclass
class RenderedSequence:
    """What :func:`render_sequence` made: the per-frame records and what the stage writes beside the frames."""

    params: RenderParams
    camera: Any
    legend: dict
    renderer_meta: dict
    frame_ev: list | None
    results: list[dict]
    workers: int

    @property
    def frames(self) -> list[dict]:
        return [r["rec"] for r in self.results]

    def metrics(self, wall_s: float) -> dict:
        """Frame count, hit and valid-flow fractions, throughput, peak memory and workers of the run."""
        hit = [r["hit"] for r in self.results]
        valid = [r["flow_valid"] for r in self.results if r["flow_valid"] is not None]
        return {"frames": len(self.results), "hit_fraction_mean": round(float(np.mean(hit)), 6),
                "flow_valid_fraction_mean": round(float(np.mean(valid)), 6) if valid else None,
                "wall_time_s": round(wall_s, 3), "frames_per_s": round(len(self.results) / wall_s, 3),
                "peak_rss_mb": round(peak_rss_mb(self.results), 1), "workers": self.workers}

    def documents(self, metadata: dict) -> dict[str, dict]:
        """The sequence's JSON files beside the frames, by catalogue name: ``legend`` (with segmentation),
        ``point_clouds`` (how clouds are stored), ``camera`` and ``render`` (``metadata``: its provenance)."""
        p = self.params
        storage = StorageParams.from_dict(p.storage)
        mods = set(p.modalities)
        # without point_cloud in render.modalities no PLY is written: the reader builds clouds from depth/ then
        stored = storage if "point_cloud" in mods else dataclasses.replace(storage, point_clouds="on_demand")
        precision = stored.precision()
        docs = {}
        if "segmentation" in mods:
            docs["legend"] = {"encoding": "uint16 PNG: label = airway branch id + 1, 0 = no hit",
                              "branch_ids": "centreline_graph.json ids", "labels": self.legend}
        docs["point_clouds"] = {**precision["point_clouds"], "requested": "point_cloud" in mods}
        docs["camera"] = {**self.camera.to_dict(), "storage": precision}
        docs["render"] = {
            "renderer": self.renderer_meta, "storage": {"params": dataclasses.asdict(storage), "precision": precision},
            "poses": p.poses, "modalities": sorted(mods), "frames": self.frames,
            "flow": "forward t -> t+1 in pixels (u right, v down); the last frame has zero flow and no valid pixel",
            "conventions": metadata_block(), "metadata": metadata}
        return docs


def render_sequence(p: RenderParams, mesh: Mesh, graph: CentrelineGraph, ts: np.ndarray, poses: np.ndarray,
                    src: np.ndarray, seq: Path, ex_params: ExecutionParams, key: str) -> RenderedSequence:
    """Render the poses ``src`` of (``ts``, ``poses``) into the sequence folder ``seq`` (module docstring)."""
    parallel = ex_params.backend != "serial" and ex_params.workers > 1
    labels, legend = face_labels(mesh, graph)
    cam = camera_of(p)
    material, light, film = scene_parts(p)
    airway = airway_coordinates(mesh.vertices, graph) if material.texture.enabled else None
    scene = Scene(mesh, cam, poses[src], ts[src], material=material, light=light, film=film,
                  face_labels=labels, vertex_airway=airway)
    film = scene.film                                   # as configured: render.json records it
    probe, ev, cycles_ev, settings = exposure_probe(scene, p)
    # every worker: the same exposures (fixed EV; the per-frame track comes with each block, metered below)
    scene.film = dataclasses.replace(scene.film, exposure_ev=ev)
    # each worker's Open3D casts and Cycles get the executor's per-worker thread budget (0: all cores)
    nthreads = ex_params.threads if parallel else 0
    cycles_threads = ex_params.threads if parallel else 0
    gather = None
    if parallel and p.indirect_bounces > 0:             # built once, by the probe above
        from .indirect import gather_cache

        gather = gather_cache()
    init = (frame_worker, (scene, p, str(seq), src, ts, poses, nthreads, cycles_ev, cycles_threads, gather))
    storage = StorageParams.from_dict(p.storage)
    # blocks small enough that every worker gets several (the executor hands out contiguous chunks of them)
    split = max(1, -(-len(src) // (4 * ex_params.workers))) if parallel else len(src)
    with make_executor(ex_params, init=init) as ex:
        frame_ev = None
        if per_frame_exposure(p):     # the meter: each frame on a worker, then smoothed in time here, in order
            from .exposure import smooth_exposures

            raw = [x for b in ex.map(meter_block, frame_blocks(len(src), split), desc=f"meter {key}") for x in b]
            frame_ev = tuple(float(x) for x in smooth_exposures(np.array([e for e, _ in raw]), scene.timestamps,
                                                                 exposure_params(p), np.array([h for _, h in raw])))
            scene.film = dataclasses.replace(scene.film, frame_ev=frame_ev)
        renderer_meta = renderer_metadata(probe, film, p, frame_ev, settings, cycles_ev)
        block = storage.write_block if not parallel else min(storage.write_block, split)
        blocks = ex.map(render_block, [(a, b, frame_ev) for a, b in frame_blocks(len(src), block)],
                        desc=f"render {key} (blocks of {block} frames)")
    return RenderedSequence(params=p, camera=cam, legend=legend, renderer_meta=renderer_meta, frame_ev=frame_ev,
                            results=[r for b in blocks for r in b], workers=ex_params.workers)
