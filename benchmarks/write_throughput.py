#!/usr/bin/env python3
"""Dataset storage: bytes per frame, write / read time and error of every codec choice, and write throughput.

Inputs: a pipeline output folder (``--data``, default ``data/output``) holding
``patient_000/anatomy/lung_model.obj``, ``anatomy/centreline_graph.json`` and
``sequence_000/metadata/simulation.json`` (what ``room run --until simulate``
writes for the default phantom patient); when absent, the phantom of
``benchmarks/raycast_renderer.py`` (1 mm, generations <= 6) and its planned
path.  Camera: the render config's default (600x600, 85 deg).

1. Codec table: ``--sample`` frames spread over the sequence, rendered once with
   every default modality (the render stage's renderer); every candidate
   encoding of every modality is written to a scratch folder and read back:
   bytes/frame, encode+write ms (CPU of the whole process and wall), read ms,
   and the maximum error against the float32 render (depth in mm, normals per
   component, flow in px).  The noisy RGB (the ``noise`` stage's default
   profile, beta 1) is measured the same way.
2. Bytes per 448-frame default sequence: the chosen (default) encodings'
   mean bytes/frame over the sample x 448 (extrapolated from the sample, not a
   full render; say so when quoting it).
3. Throughput, side by side in one run over ``--frames`` consecutive frames
   of the sequence.  The headline rows, interleaved ``--rounds`` times so all
   see the same share of the other users' load (:func:`side_by_side`): the
   bare Open3D ray cast (``RaycastingScene.create_rays_pinhole`` + ``cast_rays``
   of every pixel on the renderer's own BVH, hit distances fetched: what a user
   of Open3D alone gets) in one process and in one process per usable core (the
   same cores the stage uses), and the render stage's own fan-out
   (``frame_worker`` + ``render_block`` on the executor: render, encode,
   write) for the geometric modalities (depth, relative depth, normals, flow +
   validity, segmentation) with the default storage, with its default execution
   (``workers: 0`` resolved for the sequence: one process per core) and with one
   in-process worker.  Then, once each: the renderer's own cast alone, the
   in-process path again, with the writer threads off, with OpenImageIO's EXR
   writer, with the storage of two rounds ago (float32 EXR, .flo, ZIP, PNG level
   3, no threads), and every default modality.  Wall frames/s, CPU ms/frame of
   every process of the run (all threads), load average before/after.
   ``--quick``: only the headline rows (``write_throughput_headline.{md,json}``).
4. Memory: resident set size every 25 frames over ``--memory-frames`` frames
   (the sequence's poses repeated when it is shorter) through the same path.
5. ``--deflate``: the EXR writer's deflate (zlib 1/4/6, ISA-L 1/2, libdeflate 1/4/6) on the chunks
   of ``--deflate-frames`` real depth / normals / flow frames of the first rendered sequence in
   ``--data``: CPU ms and bytes per file, the same bytes when encoded twice, OpenImageIO reads the
   same pixels back (``write_throughput_deflate.{md,json}``).

Wall times on the shared 2-core machine include the other users' load: the
load average and the CPU time are printed next to them.

    python benchmarks/write_throughput.py [--data data/output] [--sample 12] [--frames 80] [--rounds 2]
                                          [--memory-frames 500]
    python benchmarks/write_throughput.py --quick [--data data/output] [--frames 60] [--rounds 2]
    python benchmarks/write_throughput.py --deflate [--data data/output] [--deflate-frames 8] [--deflate-repeats 3]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))

from room_pipeline.catalog import RENDER_FOLDERS, SequencePaths, find_sequences  # noqa: E402
from room_pipeline.io.atomic import write_json  # noqa: E402
from room_pipeline.io.images import (read_exr, read_flo, read_png, write_exr, write_flo, write_png8,  # noqa: E402
                                     write_png16)
from room_pipeline.io.ply import read_ply  # noqa: E402
from room_pipeline.io.storage import StorageParams, stride_mask  # noqa: E402

SEQ_FRAMES = 448
GEOMETRIC = ("depth", "relative_depth", "normals", "flow", "segmentation")
DEFAULT_MODS = ("rgb", "depth", "relative_depth", "normals", "flow", "segmentation")
GEOMETRIC_DEFAULT = "geometric modalities rendered + written, default storage"
BARE_ONE = "bare Open3D ray cast, one process (create_rays_pinhole + cast_rays, Open3D's threads)"
OLD_STORAGE = {"depth_quantum_m": 0.0, "depth_compression": "zip", "normals_dtype": "float32",
               "normals_compression": "zip", "flow_format": "flo", "png_level": 3, "write_threads": 0,
               "exr_writer": "openimageio"}


def cpu_s() -> float:
    return time.process_time()


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def load_inputs(args):
    """(mesh, face labels, legend, poses, timestamps, description)."""
    from room_pipeline.anatomy.centreline import CentrelineGraph
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.sequence import face_labels

    from room_pipeline.io.records import pose_track
    from room_pipeline.paths import PatientPaths

    pp = PatientPaths(Path(args.data), "patient_000")
    sim = pp.seq("sequence_000").simulation
    if pp.mesh.is_file() and sim.is_file():
        mesh = read_obj(pp.mesh)
        labels, _ = face_labels(mesh, CentrelineGraph.from_dict(json.loads(pp.centreline_graph.read_text())))
        track = pose_track(sim)
        poses, ts = track.poses, track.timestamps
        return mesh, labels, poses, ts, {"source": str(pp.root), "poses": "simulated (sequence_000)",
                                         "faces": int(mesh.n_faces), "frames": len(poses)}
    from raycast_renderer import make_inputs

    mesh, poses, ts, info = make_inputs(argparse.Namespace(obj=None, trajectory=None))
    return mesh, None, poses, ts, {"source": "benchmarks/raycast_renderer.py phantom", **info,
                                   "faces": int(mesh.n_faces), "frames": len(poses)}


def make_scene(mesh, labels, poses, ts):
    from omegaconf import OmegaConf

    from room_pipeline.config.compose import section
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial
    from room_pipeline.render.params import RenderParams, texture_params

    cfg = OmegaConf.load(ROOT / "params.yaml")
    p = RenderParams.from_dict(section(cfg, "render"))
    cam = CameraIntrinsics.from_fov(p.width, p.height, p.fov_deg, p.near_mm * 1e-3, p.far_mm * 1e-3)
    scene = Scene(mesh, cam, poses, ts,
                  material=TissueMaterial(base_color=tuple(p.base_color), roughness=p.roughness,
                                          specular=p.specular, texture=texture_params(p.texture)),
                  light=TipLight(power_w=p.light_power_w, radius_m=p.light_radius_mm * 1e-3),
                  film=Film(exposure_ev=p.exposure_ev, auto_target=p.auto_exposure_target), face_labels=labels)
    return scene, p


# --------------------------------------------------------------------------- 1. codecs


def timed(fn, *a, **kw):
    c0, w0 = cpu_s(), time.perf_counter()
    out = fn(*a, **kw)
    return out, 1e3 * (cpu_s() - c0), 1e3 * (time.perf_counter() - w0)


def codec_table(frames: list[dict], tmp: Path) -> list[dict]:
    """Every candidate encoding of every modality over the sampled frames."""
    cands = []

    def exr(mod, arr_key, label, prep, half, comp, err_fn, channels=None, default=False, writer="openimageio"):
        cands.append((mod, label + (", libdeflate writer" if writer == "libdeflate" else ""), default,
                      lambda f, p: write_exr(p, prep(f), channels=channels, half=half, compression=comp,
                                             writer=writer),
                      lambda p: read_exr(p)[0], err_fn, ".exr"))

    q17, q16 = 2.0 ** -17, 2.0 ** -16

    def rounded(q):
        return lambda f: StorageParams(depth_quantum_m=q).depth_array(f["depth"], f["hit"])

    raw_depth = lambda f: np.where(f["hit"], f["depth"], 0).astype(np.float32)  # noqa: E731
    depth_err = lambda f, a: 1e3 * float(np.abs(a.astype(np.float64) - f["depth"].astype(np.float64))[f["hit"]].max())  # noqa: E731,E501
    for comp in ("none", "zip", "piz", "zips"):
        exr("depth", "depth", f"float32 {comp}", raw_depth, False, comp, depth_err, ("Y",))
    for comp in ("zip", "zip:1", "piz", "pxr24"):
        exr("depth", "depth", f"float32 rounded 2^-17 m, {comp}", rounded(q17), False, comp, depth_err, ("Y",))
    for comp in ("zip", "pxr24"):
        exr("depth", "depth", f"float32 rounded 2^-17 m, {comp}", rounded(q17), False, comp, depth_err, ("Y",),
            default=comp == "pxr24", writer="libdeflate")
    exr("depth", "depth", "float32 rounded 2^-16 m, zip", rounded(q16), False, "zip", depth_err, ("Y",))
    exr("depth", "depth", "float32 pxr24 (lossy 24-bit)", raw_depth, False, "pxr24", depth_err, ("Y",))
    exr("depth", "depth", "half zip", raw_depth, True, "zip", depth_err, ("Y",))

    nrm = lambda f: f["normals"]  # noqa: E731
    nrm_err = lambda f, a: float(np.abs(a - f["normals"]).max())  # noqa: E731
    exr("normals", "normals", "float32 zip (before)", nrm, False, "zip", nrm_err)
    for comp in ("zip", "zip:1", "piz", "zips", "pxr24"):
        exr("normals", "normals", f"half {comp}", nrm, True, comp, nrm_err)
    for comp in ("zip", "zips", "pxr24"):
        exr("normals", "normals", f"half {comp}", nrm, True, comp, nrm_err, default=comp == "pxr24", writer="libdeflate")
    exr("normals", "normals", "half dwaa (lossy)", nrm, True, "dwaa", nrm_err)

    flw = lambda f: f["flow"]  # noqa: E731
    flow_err = lambda f, a: float(np.abs(a - f["flow"]).max())  # noqa: E731
    cands.append(("flow", ".flo float32 (before)", False, lambda f, p: write_flo(p, f["flow"]), read_flo, flow_err,
                  ".flo"))
    exr("flow", "flow", "float32 zip", flw, False, "zip", flow_err, ("R", "G"))
    for comp in ("zip", "zip:1", "piz", "zips", "pxr24"):
        exr("flow", "flow", f"half {comp}", flw, True, comp, flow_err, ("R", "G"))
    for comp in ("zip", "zips", "pxr24"):
        exr("flow", "flow", f"half {comp}", flw, True, comp, flow_err, ("R", "G"), default=comp == "pxr24",
            writer="libdeflate")
    # the noise stage writes rgb_noisy with write_png8's default level (io.images.PNG_COMPRESSION)
    from room_pipeline.io.images import PNG_COMPRESSION

    png_default = StorageParams().png_level
    for lvl in (1, 3, 6, 9):
        cands.append(("rgb", f"png level {lvl}", lvl == png_default, lambda f, p, l=lvl: write_png8(p, f["rgb"], l),
                      read_png, lambda f, a: float(np.abs(a.astype(int) - f["rgb"]).max()), ".png"))
        cands.append(("rgb_noisy", f"png level {lvl}", lvl == PNG_COMPRESSION,
                      lambda f, p, l=lvl: write_png8(p, f["rgb_noisy"], l),
                      read_png, lambda f, a: float(np.abs(a.astype(int) - f["rgb_noisy"]).max()), ".png"))
        cands.append(("relative_depth", f"png16 level {lvl}", lvl == png_default,
                      lambda f, p, l=lvl: write_png16(p, f["relative_depth"], l), read_png,
                      lambda f, a: float(np.abs(a.astype(int) - f["relative_depth"]).max()), ".png"))
    seg = lambda f: (f["segmentation"] + 1).astype(np.uint16)  # noqa: E731
    vld = lambda f: f["flow_valid"].astype(np.uint8) * 255  # noqa: E731
    for rle in (False, True):
        tag = f"level {png_default}" + (", RLE strategy" if rle else "")
        cands.append(("segmentation", f"png16 {tag}", rle, lambda f, p, r=rle: write_png16(p, seg(f), png_default, r),
                      read_png, lambda f, a: float(np.abs(a.astype(int) - seg(f)).max()), ".png"))
        cands.append(("flow_valid", f"png {tag}", rle, lambda f, p, r=rle: write_png8(p, vld(f), png_default, r),
                      read_png, lambda f, a: float(np.abs(a.astype(int) - vld(f)).max()), ".png"))
    from room_pipeline.render.raycast import write_point_cloud

    for s in (1, 2, 4):
        def w_pc(f, p, s=s):
            keep = stride_mask(f["hit"], s)[f["hit"]]
            write_point_cloud(p, {k: v[keep] for k, v in f.items() if k.startswith("point_cloud")})
        cands.append(("point_cloud", f"ply stride {s}", False, w_pc, lambda p: read_ply(p)[0]["z"],
                      lambda f, a, s=s: 0.0, ".ply"))
    rows = []
    for mod, label, default, write, read, err, ext in cands:
        nbytes, wc, ww, rw, worst = [], [], [], [], 0.0
        for k, f in enumerate(frames):
            path = tmp / f"{mod}_{k}{ext}"
            _, c, w = timed(write, f, path)
            nbytes.append(path.stat().st_size)
            wc.append(c)
            ww.append(w)
            a, _, r = timed(read, path)
            rw.append(r)
            worst = max(worst, err(f, a))
            path.unlink()
        rows.append({"modality": mod, "encoding": label, "default": default,
                     "bytes_per_frame": int(np.mean(nbytes)), "write_cpu_ms": round(float(np.mean(wc)), 2),
                     "write_wall_ms": round(float(np.mean(ww)), 2), "read_wall_ms": round(float(np.mean(rw)), 2),
                     "max_error": worst})
        print(f"  {mod:15s} {label:34s} {rows[-1]['bytes_per_frame']:>9d} B  write {rows[-1]['write_wall_ms']:7.2f} ms "
              f"(cpu {rows[-1]['write_cpu_ms']:6.2f})  read {rows[-1]['read_wall_ms']:6.2f} ms  max err {worst:.3g}",
              flush=True)
    return rows


# --------------------------------------------------------------------------- 3. throughput


def bare_cast(scene, frames: list[int], label: str = BARE_ONE) -> dict:
    """The floor: Open3D alone, as a user of it would cast a depth image, on the same BVH and poses.

    ``RaycastingScene.create_rays_pinhole(K, world-to-camera, W, H)`` then ``cast_rays`` (all cores) and the
    hit distances fetched as a NumPy array: no near plane, no other output used.
    """
    import open3d as o3d

    from room_pipeline.render.raycast import RaycastRenderer

    r = RaycastRenderer(scene)                                     # its Open3D scene: the same BVH
    cam = scene.camera
    K = o3d.core.Tensor(cam.K)

    def one(i: int):
        pose = np.array(scene.poses[i], dtype=np.float64)
        pose[:3, 3] -= r.origin
        rays = r._rc.create_rays_pinhole(K, o3d.core.Tensor(np.linalg.inv(pose)), cam.width, cam.height)
        return r._rc.cast_rays(rays)["t_hit"].numpy()

    one(frames[0])                                                 # warm-up
    c0, w0 = cpu_s(), time.perf_counter()
    for i in frames:
        one(i)
    return {"run": label, "frames": len(frames), "wall_s": time.perf_counter() - w0, "cpu_s": cpu_s() - c0}


def own_cast(scene, frames: list[int]) -> dict:
    """The renderer's own cast of every pixel (pixel_rays table, near-plane origins), nothing else."""
    from room_pipeline.render.raycast import RaycastRenderer

    r = RaycastRenderer(scene)
    r._cast_rays(scene.poses[frames[0]], r._rays32)               # warm-up
    c0, w0 = cpu_s(), time.perf_counter()
    for i in frames:
        r._cast_rays(scene.poses[i], r._rays32)["t_hit"].numpy()
    return {"run": "renderer's cast alone (RaycastRenderer._cast_rays)", "frames": len(frames),
            "wall_s": time.perf_counter() - w0, "cpu_s": cpu_s() - c0}


def side_by_side(scene, p, tmp: Path, frames: list[int], ev: float, rounds: int) -> list[dict]:
    """The headline runs, interleaved ``rounds`` times so all see the same share of the other users' load.

    1. the bare Open3D cast in one process (Open3D's own threads: ``cast_rays`` with its default
       ``nthreads=0``, all cores); 2. the bare cast in one process per usable core (contiguous halves of the
       frames, each process its own BVH): the strongest 2-core reference, since ``cast_rays`` holds the GIL
       and Open3D's own threads do not make one cast faster (CPU ~ wall); 3. the geometric modalities rendered
       and written by the render stage with its default execution (``workers: 0`` resolved for this
       sequence's length, as ``render.run`` does: one local worker process per core); 4. the same with one
       in-process worker (``execution.workers=1``, the previous default).  Each row sums its rounds.
    """
    from _throughput_parallel import bare_cast_processes

    from room_pipeline.execution import ExecutionParams
    from room_pipeline.execution.executor import usable_cores

    cores = usable_cores()
    workers = ExecutionParams().resolved(len(scene.poses)).workers
    total: dict[str, dict] = {}
    for _ in range(rounds):
        bare_n = {**bare_cast_processes(scene, frames, cores),
                  "run": f"bare Open3D ray cast, {cores} processes (one per core)"}
        for run in (bare_cast(scene, frames, BARE_ONE), bare_n,
                    stage_workers(scene, p, tmp / "seq", GEOMETRIC, {}, frames,
                                  f"{GEOMETRIC_DEFAULT}, default execution ({workers} worker process"
                                  f"{'es' if workers > 1 else ''})", ev, workers),
                    stage_workers(scene, p, tmp / "seq", GEOMETRIC, {}, frames,
                                  "geometric, default storage, one in-process worker (execution.workers=1)", ev, 1)):
            t = total.setdefault(run["run"], {**run, "frames": 0, "wall_s": 0.0, "cpu_s": 0.0, "rounds": 0,
                                              "startup_s": 0.0})
            t["frames"] += run["frames"]
            t["wall_s"] += run["wall_s"]
            t["cpu_s"] += run["cpu_s"]
            t["startup_s"] += run.get("startup_s", 0.0)
            t["rounds"] += 1
    return list(total.values())


def rates(runs: list[dict]) -> list[dict]:
    """frames/s, ms/frame and the fraction of the bare cast's throughput (first row) of every run."""
    for r in runs:
        r["fps"] = r["frames"] / r["wall_s"]
        r["cpu_ms_per_frame"] = 1e3 * r["cpu_s"] / r["frames"]
        r["wall_ms_per_frame"] = 1e3 * r["wall_s"] / r["frames"]
    bare_fps, bare_cpu = runs[0]["fps"], runs[0]["cpu_ms_per_frame"]
    best = max((r for r in runs if r["run"].startswith("bare")), key=lambda r: r["fps"])
    for r in runs:
        r["fraction_of_bare_wall"] = r["fps"] / bare_fps
        r["fraction_of_bare_cpu"] = bare_cpu / r["cpu_ms_per_frame"]
        r["fraction_of_best_bare_wall"] = r["fps"] / best["fps"]
    return runs


def stage_path(scene, p, seq: Path, mods, storage: dict, frames: list[int], label: str, ev: float,
               rss_every: int = 0) -> dict:
    """The render stage's per-frame path (worker state, blocks, writer) over ``frames``."""
    from room_pipeline.render import sequence as rs

    p2 = dataclasses.replace(p, modalities=tuple(mods), storage={**p.storage, **storage})
    st = StorageParams.from_dict(p2.storage)
    scene.film = dataclasses.replace(scene.film, exposure_ev=ev)
    src = np.arange(len(scene.poses))
    state = rs.frame_worker(scene, p2, str(seq), src, scene.timestamps, scene.poses, 0, None, 0)
    for f in RENDER_FOLDERS.values():
        (seq / f).mkdir(parents=True, exist_ok=True)
    last = len(scene.poses) - 1                                    # warm-up (normal tables, threads) on a frame
    rs.render_block(state, (last, last + 1))                      # outside the run: no cast of the run cached
    rss = []
    c0, w0 = cpu_s(), time.perf_counter()
    start, stop = frames[0], frames[-1] + 1
    for b0 in range(start, stop, st.write_block):
        rs.render_block(state, (b0, min(b0 + st.write_block, stop)))
        if rss_every and (b0 - start) % rss_every < st.write_block:
            rss.append((b0 - start, round(rss_mb(), 1)))
    wall, cpu = time.perf_counter() - w0, cpu_s() - c0
    state["writer"].close()
    nbytes = sum(f.stat().st_size for f in seq.rglob("frame_*") if f.is_file()) + \
        sum(f.stat().st_size for f in seq.rglob("valid_*") if f.is_file())
    shutil.rmtree(seq)
    out = {"run": label, "frames": len(frames), "wall_s": wall, "cpu_s": cpu,
           "bytes_per_frame": nbytes / (len(frames) + 1)}
    if rss:
        out["rss_mb"] = rss
    return out


def stage_workers(scene, p, seq: Path, mods, storage: dict, frames: list[int], label: str, ev: float,
                  workers: int) -> dict:
    """The render stage's fan-out (``render.run``'s executor, blocks and worker state) over ``frames``.

    ``workers`` local processes (``execution.backend: local``, one library thread each as
    ``threads_per_worker: 0`` gives on 2 cores), or the in-process worker when ``workers`` is 1 (what
    ``render.run`` does then).  The workers are started and warmed up (one block each, outside ``frames``)
    before the clock starts; their start-up is reported apart.  CPU = the driver's plus each worker's CPU
    over its blocks (all threads; every block's files are on disk when it returns).
    """
    from _throughput_parallel import timed_render_block

    from room_pipeline.execution import ExecutionParams, make_executor
    from room_pipeline.render import sequence as rs

    p2 = dataclasses.replace(p, modalities=tuple(mods), storage={**p.storage, **storage})
    st = StorageParams.from_dict(p2.storage)
    scene.film = dataclasses.replace(scene.film, exposure_ev=ev)
    src = np.arange(len(scene.poses))
    ex_params = ExecutionParams(backend="local" if workers > 1 else "serial", workers=workers)
    parallel = workers > 1
    nthreads = ex_params.threads if parallel else 0
    for f in RENDER_FOLDERS.values():
        (seq / f).mkdir(parents=True, exist_ok=True)
    init = (rs.frame_worker, (scene, p2, str(seq), src, scene.timestamps, scene.poses, nthreads, None, nthreads))
    start, stop = frames[0], frames[-1] + 1
    block = st.write_block if not parallel else max(1, min(st.write_block, -(-len(frames) // (4 * workers))))
    last = len(scene.poses) - 1
    w_start = time.perf_counter()
    with make_executor(ex_params, init=init) as ex:
        ex.map(timed_render_block, [(last, last + 1)] * (2 * workers))      # start and warm up every worker
        startup = time.perf_counter() - w_start
        c0, w0 = cpu_s(), time.perf_counter()
        res = ex.map(timed_render_block, [(b, min(b + block, stop)) for b in range(start, stop, block)])
        wall, cpu = time.perf_counter() - w0, cpu_s() - c0
    if parallel:
        cpu += sum(r[1] for r in res)
    nbytes = sum(f.stat().st_size for f in seq.rglob("frame_*") if f.is_file()) + \
        sum(f.stat().st_size for f in seq.rglob("valid_*") if f.is_file())
    shutil.rmtree(seq)
    return {"run": label, "frames": len(frames), "wall_s": wall, "cpu_s": cpu, "workers": workers,
            "startup_s": startup, "bytes_per_frame": nbytes / (len(frames) + 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "output"))
    ap.add_argument("--sample", type=int, default=12, help="frames for the codec table")
    ap.add_argument("--frames", type=int, default=80, help="consecutive frames for the throughput runs")
    ap.add_argument("--memory-frames", type=int, default=500)
    ap.add_argument("--tmp", default=None, help="scratch folder (default: a temporary folder)")
    ap.add_argument("--memory-only", action="store_true",
                    help="only part 4; results in write_throughput_memory.{md,json}")
    ap.add_argument("--rounds", type=int, default=2,
                    help="interleaved rounds of the headline pair (bare cast, geometric rendered + written)")
    ap.add_argument("--quick", action="store_true",
                    help="only the headline pair (part 3's first two rows); results in "
                         "write_throughput_headline.{md,json}")
    ap.add_argument("--deflate", action="store_true",
                    help="only part 5: the deflate codecs on the EXR frames of the first rendered sequence in --data; "
                         "results in write_throughput_deflate.{md,json}")
    ap.add_argument("--deflate-frames", type=int, default=8, help="part 5: frames per EXR folder")
    ap.add_argument("--deflate-repeats", type=int, default=3, help="part 5: encodings of each frame per codec")
    args = ap.parse_args()
    if args.deflate:
        deflate_table(args)
        return
    if args.memory_only:
        memory_only(args)
        return
    if args.quick:
        headline(args)
        return

    from room_pipeline.noise.profile import NoiseProfile
    from room_pipeline.noise.synthesize import add_noise
    from room_pipeline.render.raycast import RaycastRenderer
    from room_pipeline.stages.noise import NoiseParams, frame_seed, resolve_profile
    from room_pipeline.render.sequence import Renderers as _Renderers

    load0 = os.getloadavg()
    mesh, labels, poses, ts, info = load_inputs(args)
    scene, p = make_scene(mesh, labels, poses, ts)
    n = len(poses)
    print(f"inputs: {info}", flush=True)
    ev = RaycastRenderer(scene).exposure_ev
    scene.film = dataclasses.replace(scene.film, exposure_ev=ev)
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="room_write_"))
    tmp.mkdir(parents=True, exist_ok=True)

    # 1. codecs on sampled frames (every modality from one render, one cast per frame + the next for flow)
    rend = _Renderers(scene, p)
    nprm = NoiseParams()
    profile = NoiseProfile.load(resolve_profile(nprm.profile))
    sample = np.unique(np.linspace(0, n - 2, args.sample).round().astype(int)).tolist()
    frames = []
    for i in sample:
        out = rend.render(i, set(DEFAULT_MODS) | {"point_cloud"})
        out["depth"] = out["depth"].copy()
        out["rgb_noisy"] = add_noise(out["rgb"], profile, nprm.beta, frame_seed(nprm.seed, "sequence_000", i))
        frames.append(out)
    print(f"codec table over frames {sample}", flush=True)
    rows = codec_table(frames, tmp)
    del frames

    # 2. bytes per default sequence (from the sample)
    chosen = {r["modality"]: r for r in rows if r["default"]}
    per_frame = {m: chosen[m]["bytes_per_frame"] for m in chosen}
    before = {"depth": "float32 zip", "normals": "float32 zip (before)", "flow": ".flo float32 (before)"}
    old = dict(per_frame)
    for m, lab in before.items():
        old[m] = next(r["bytes_per_frame"] for r in rows if r["modality"] == m and r["encoding"] == lab)
    seq_bytes, old_bytes = SEQ_FRAMES * sum(per_frame.values()), SEQ_FRAMES * sum(old.values())

    # 3. throughput side by side (the headline pair interleaved, then the variants)
    tframes = throughput_frames(n, args.frames)
    seq = tmp / "seq"
    runs = side_by_side(scene, p, tmp, tframes, ev, args.rounds)
    runs.append(own_cast(scene, tframes))
    runs.append(stage_path(scene, p, seq, GEOMETRIC, {}, tframes,
                           "geometric, default storage, one in-process worker (again, not interleaved)", ev))
    runs.append(stage_path(scene, p, seq, GEOMETRIC, {"write_threads": 0}, tframes,
                           "geometric, default storage, one in-process worker, writer threads off", ev))
    runs.append(stage_path(scene, p, seq, GEOMETRIC, {"exr_writer": "openimageio"}, tframes,
                           "geometric, one in-process worker, OpenImageIO's EXR writer (the previous round's)", ev))
    runs.append(stage_path(scene, p, seq, GEOMETRIC, OLD_STORAGE, tframes,
                           "geometric, previous storage (float32 EXR, .flo, no threads)", ev))
    from room_pipeline.execution import ExecutionParams

    workers = ExecutionParams().resolved(n).workers
    runs.append(stage_workers(scene, p, seq, DEFAULT_MODS, {}, tframes,
                              f"every default modality, default storage, default execution ({workers} workers)", ev,
                              workers))
    rates(runs)

    # 4. memory over many frames (poses repeated)
    mem = None
    if args.memory_frames > 0:
        reps = int(np.ceil((args.memory_frames + 1) / n))
        big, _ = make_scene(mesh, labels, np.tile(poses, (reps, 1, 1)), np.arange(n * reps) * 0.1)
        mem = stage_path(big, p, seq, DEFAULT_MODS, {}, list(range(args.memory_frames)),
                         f"memory: every default modality over {args.memory_frames} frames", ev, rss_every=25)
    load1 = os.getloadavg()
    shutil.rmtree(tmp, ignore_errors=True)

    res = {"inputs": info, "camera": scene.camera.to_dict(), "sample_frames": sample, "codecs": rows,
           "default_bytes_per_frame": per_frame, "sequence_frames": SEQ_FRAMES,
           "default_sequence_bytes": seq_bytes, "previous_sequence_bytes": old_bytes,
           "throughput_frames": [tframes[0], tframes[-1]], "throughput": runs, "memory": mem,
           "load_average_before": load0, "load_average_after": load1, "cpu_count": os.cpu_count(),
           "machine": platform.platform(),
           "command": "python benchmarks/write_throughput.py " + " ".join(sys.argv[1:])}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "write_throughput.json", res)
    (RESULTS / "write_throughput.md").write_text(markdown(res))
    print(markdown(res))


def throughput_frames(n: int, frames: int) -> list[int]:
    """``frames`` consecutive frames from a third of the way into the sequence (each has a successor: flow)."""
    start = min(max(0, n // 3), max(0, n - frames - 2))
    return list(range(start, min(n - 1, start + frames)))


def headline(args) -> None:
    """The two headline numbers, measured side by side in one run (about 1-3 minutes on 2 cores)."""
    from room_pipeline.render.raycast import RaycastRenderer

    load0 = os.getloadavg()
    mesh, labels, poses, ts, info = load_inputs(args)
    scene, p = make_scene(mesh, labels, poses, ts)
    ev = RaycastRenderer(scene).exposure_ev
    scene.film = dataclasses.replace(scene.film, exposure_ev=ev)
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="room_write_quick_"))
    tframes = throughput_frames(len(poses), args.frames)
    runs = rates(side_by_side(scene, p, tmp, tframes, ev, args.rounds))
    shutil.rmtree(tmp, ignore_errors=True)
    res = {"inputs": info, "camera": scene.camera.to_dict(), "throughput_frames": [tframes[0], tframes[-1]],
           "rounds": args.rounds, "throughput": runs, "load_average_before": load0,
           "load_average_after": os.getloadavg(), "cpu_count": os.cpu_count(), "machine": platform.platform(),
           "command": "python benchmarks/write_throughput.py " + " ".join(sys.argv[1:])}
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "write_throughput_headline.json", res)
    md = headline_markdown(res)
    (RESULTS / "write_throughput_headline.md").write_text(md)
    print(md)


def headline_markdown(res: dict) -> str:
    i = res["inputs"]
    runs = res["throughput"]
    bare1, bare_n, geo, geo1 = runs[0], runs[1], runs[2], runs[3]
    t0, t1 = res["throughput_frames"]
    L = ["# Write throughput: geometric modalities rendered + written vs the bare Open3D ray cast", "",
         f"`{res['command']}`.  Inputs: {i['source']} ({i['faces']} faces), frames {t0}..{t1} in order, "
         f"{res['rounds']} interleaved rounds; camera {res['camera']['width']}x{res['camera']['height']}.  "
         f"Load average {res['load_average_before'][0]:.2f} -> {res['load_average_after'][0]:.2f} on "
         f"{res['cpu_count']} cores (wall times include other users' load; CPU times are those of every process "
         f"of the run, all their threads).  Geometric modalities: depth, relative depth, normals, flow + validity, "
         f"segmentation, every file written (default `render.storage`).  Worker start-up (spawn, imports, BVH) is "
         f"outside the timed frames, as the bare casts' BVH build is; it is listed apart.", "",
         "| run | frames/s (wall) | wall ms/frame | CPU ms/frame | vs bare cast, 1 process (wall) | "
         "vs bare cast, one process per core (wall) | vs bare cast, 1 process (CPU) | start-up s |",
         "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        su = f"{r['startup_s'] / r['rounds']:.1f}" if r.get("startup_s") else ""
        L.append(f"| {r['run']} | {r['fps']:.2f} | {r['wall_ms_per_frame']:.1f} | {r['cpu_ms_per_frame']:.1f} | "
                 f"{100 * r['fraction_of_bare_wall']:.0f} % | {100 * r['fps'] / bare_n['fps']:.0f} % | "
                 f"{100 * r['fraction_of_bare_cpu']:.0f} % | {su} |")
    L += ["", f"Headline: **{geo['fps']:.2f} frames/s** written for the geometric modalities with the default "
              f"execution (target >= 12 on 2 cores), **{100 * geo['fps'] / bare_n['fps']:.0f} %** of the bare "
              f"cast given the same cores ({bare_n['fps']:.2f} frames/s, one process per core; target >= 40 %) "
              f"and {100 * geo['fraction_of_bare_wall']:.0f} % of the one-process bare cast "
              f"({bare1['fps']:.2f} frames/s).  CPU: {geo['cpu_ms_per_frame']:.1f} ms/frame written vs "
              f"{bare1['cpu_ms_per_frame']:.1f} bare; on a quiet machine with C cores the written rate is bounded "
              f"by C x 1000 / {geo['cpu_ms_per_frame']:.1f} = {2000 / geo['cpu_ms_per_frame']:.1f} frames/s "
              f"for C = 2.  One in-process worker: {geo1['fps']:.2f} frames/s, {geo1['cpu_ms_per_frame']:.1f} "
              f"CPU ms/frame."]
    return "\n".join(L) + "\n"


def memory_only(args) -> None:
    from room_pipeline.render.raycast import RaycastRenderer

    load0 = os.getloadavg()
    mesh, labels, poses, ts, info = load_inputs(args)
    n = len(poses)
    reps = int(np.ceil((args.memory_frames + 1) / n))
    big, p = make_scene(mesh, labels, np.tile(poses, (reps, 1, 1)), np.arange(n * reps) * 0.1)
    ev = RaycastRenderer(big).exposure_ev
    tmp = Path(args.tmp or tempfile.mkdtemp(prefix="room_write_mem_"))
    m = stage_path(big, p, tmp / "seq", DEFAULT_MODS, {}, list(range(args.memory_frames)),
                   f"memory: every default modality over {args.memory_frames} frames", ev, rss_every=25)
    shutil.rmtree(tmp, ignore_errors=True)
    res = {"inputs": info, "memory": m, "load_average_before": load0, "load_average_after": os.getloadavg(),
           "command": "python benchmarks/write_throughput.py " + " ".join(sys.argv[1:])}
    rss = m["rss_mb"]
    vals = [v for _, v in rss]
    md = "\n".join([f"# Render-stage memory over {m['frames']} frames", "", f"`{res['command']}`; inputs "
                    f"{info['source']} (poses repeated past {n}); load average {load0[0]:.2f} -> "
                    f"{res['load_average_after'][0]:.2f}.", "",
                    f"Resident set size every 25 frames (MB): first {vals[0]}, last {vals[-1]}, max {max(vals)}, "
                    f"last - first {vals[-1] - vals[0]:+.1f}; {m['frames'] / m['wall_s']:.2f} frames/s wall, "
                    f"{1e3 * m['cpu_s'] / m['frames']:.1f} CPU ms/frame.", "",
                    "frame: MB  " + ", ".join(f"{k}: {v}" for k, v in rss)]) + "\n"
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "write_throughput_memory.json", res)
    (RESULTS / "write_throughput_memory.md").write_text(md)
    print(md)


def markdown(res: dict) -> str:
    i = res["inputs"]
    L = [f"# Dataset storage: bytes, codecs, write throughput",
         "",
         f"`{res['command']}`.  Inputs: {i['source']} ({i['faces']} faces, {i['frames']} poses); camera "
         f"{res['camera']['width']}x{res['camera']['height']}.  Load average {res['load_average_before'][0]:.2f} "
         f"-> {res['load_average_after'][0]:.2f} on {res['cpu_count']} cores shared with other users: wall times "
         f"include their load, CPU times are this process's (all its threads).",
         "",
         f"## Codecs (mean over {len(res['sample_frames'])} frames spread over the sequence; ** = default)",
         "",
         "Errors against the float32 render: depth in mm, normals per component, flow in px, PNG in levels.",
         "",
         "| modality | encoding | bytes/frame | write ms (wall) | write ms (CPU) | read ms | max error |",
         "|---|---|---|---|---|---|---|"]
    for r in res["codecs"]:
        mark = "**" if r["default"] else ""
        L.append(f"| {r['modality']} | {mark}{r['encoding']}{mark} | {r['bytes_per_frame']:,} | {r['write_wall_ms']} "
                 f"| {r['write_cpu_ms']} | {r['read_wall_ms']} | {r['max_error']:.3g} |")
    pf = res["default_bytes_per_frame"]
    L += ["", f"## Bytes per {res['sequence_frames']}-frame default sequence (extrapolated from the sample)", "",
          "| modality | bytes/frame | per sequence (MB) |", "|---|---|---|"]
    for m, b in pf.items():
        L.append(f"| {m} | {b:,} | {b * res['sequence_frames'] / 1e6:.1f} |")
    L.append(f"| **total** | {sum(pf.values()):,} | **{res['default_sequence_bytes'] / 1e6:.1f}** |")
    L += ["", f"Previous storage (float32 depth and normals EXR, .flo): "
              f"{res['previous_sequence_bytes'] / 1e6:.1f} MB per sequence.  Point clouds are built on demand "
              f"(0 bytes); a compact PLY would add the point_cloud row per frame.", ""]
    t0, t1 = res["throughput_frames"]
    L += [f"## Write throughput, side by side (frames {t0}..{t1}, in order)", "",
          "| run | frames/s (wall) | wall ms/frame | CPU ms/frame | vs bare cast, 1 process (wall) | "
          "vs fastest bare cast (wall) | vs bare cast, 1 process (CPU) | bytes/frame |",
          "|---|---|---|---|---|---|---|---|"]
    for r in res["throughput"]:
        b = f"{int(r['bytes_per_frame']):,}" if "bytes_per_frame" in r else ""
        L.append(f"| {r['run']} | {r['fps']:.2f} | {r['wall_ms_per_frame']:.1f} | {r['cpu_ms_per_frame']:.1f} | "
                 f"{100 * r['fraction_of_bare_wall']:.0f} % | {100 * r['fraction_of_best_bare_wall']:.0f} % | "
                 f"{100 * r['fraction_of_bare_cpu']:.0f} % | {b} |")
    m = res["memory"]
    if m:
        rss = m["rss_mb"]
        vals = [v for _, v in rss]
        L += ["", f"## Memory ({m['run']})", "",
              f"Resident set size every 25 frames (MB): first {vals[0]}, after frame {rss[len(rss) // 2][0]} "
              f"{rss[len(rss) // 2][1]}, last {vals[-1]}, max {max(vals)}; "
              f"{m['frames'] / m['wall_s']:.2f} frames/s, {1e3 * m['cpu_s'] / m['frames']:.1f} CPU ms/frame.", "",
              "frame: MB  " + ", ".join(f"{k}: {v}" for k, v in rss)]
    return "\n".join(L) + "\n"



#: part 5's codecs: label -> (package, level); "libdeflate" is the writer's (room_pipeline.io.exr.deflate_zlib)
DEFLATE_CODECS = {"zlib 1": ("zlib", 1), "zlib 4": ("zlib", 4), "zlib 6": ("zlib", 6),
                  "ISA-L 1 (the writer until session 11)": ("isal", 1), "ISA-L 2": ("isal", 2),
                  "libdeflate 1": ("libdeflate", 1), "libdeflate 4": ("libdeflate", 4),
                  "libdeflate 6": ("libdeflate", 6)}


def _deflater(package: str, level: int):
    """A chunk encoder (bytes -> zlib stream), or None when its package is not installed."""
    if package == "zlib":
        import zlib
        return lambda b: zlib.compress(b, level)
    if package == "isal":
        try:
            from isal import isal_zlib
        except ImportError:
            return None
        return lambda b: isal_zlib.compress(b, level)
    from room_pipeline.io.exr import deflate_zlib
    return lambda b: deflate_zlib(b, level)


def _exr_inputs(data: Path, limit: int) -> list[tuple[Path, np.ndarray, tuple[str, ...], bool, str]]:
    """Up to ``limit`` EXR frames per EXR folder of the first rendered sequence under ``data``:
    (path, pixels, channels, half, compression) as OpenImageIO reads them."""
    import OpenImageIO as oiio

    seq = next((s.root for s in find_sequences(data)), None)
    if seq is None:
        raise SystemExit(f"room: error: {data}: no rendered sequence (run `room run` or `dvc repro` first)")
    out = []
    for mod in ("depth", "normals", "flow"):
        files = sorted(SequencePaths(seq).folder(mod).glob("*.exr"))
        step = max(1, len(files) // max(limit, 1))
        for f in files[::step][:limit]:
            arr, names, _ = read_exr(f)
            inp = oiio.ImageInput.open(str(f))
            spec = inp.spec()
            inp.close()
            out.append((f, arr, names, spec.format == oiio.HALF, spec.get_string_attribute("compression")))
    return out


def deflate_table(args) -> None:
    """Part 5: every deflate codec on the chunks of real EXR frames: bytes, encode CPU, determinism, reading."""
    from room_pipeline.io.exr import encode_exr

    inputs = _exr_inputs(Path(args.data), args.deflate_frames)
    load0 = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        for label, (package, level) in DEFLATE_CODECS.items():
            enc = _deflater(package, level)
            if enc is None:
                rows.append({"codec": label, "skipped": f"{package} is not installed"})
                continue
            row = {"codec": label, "files": 0, "bytes": 0, "cpu_ms": 0.0, "repeat_identical": True,
                   "reads_back_equal": True}
            by_mod: dict[str, int] = {}
            for f, arr, names, half, comp in inputs:
                c0 = cpu_s()
                for _ in range(args.deflate_repeats):
                    b = encode_exr(arr, names, half, comp, deflate=enc)
                row["cpu_ms"] += 1e3 * (cpu_s() - c0) / args.deflate_repeats
                row["repeat_identical"] &= encode_exr(arr, names, half, comp, deflate=enc) == b
                row["files"] += 1
                row["bytes"] += len(b)
                by_mod[f.parent.name] = by_mod.get(f.parent.name, 0) + len(b)
                back = Path(tmp) / f"{len(rows)}_{f.parent.name}_{f.name}"
                back.write_bytes(b)
                row["reads_back_equal"] &= bool(np.array_equal(read_exr(back)[0], arr, equal_nan=True))
            row["bytes_per_folder"] = by_mod
            rows.append(row)
    res = {"inputs": sorted({str(f.parent.relative_to(Path(args.data))) for f, *_ in inputs}),
           "files": len(inputs), "repeats": args.deflate_repeats, "rows": rows,
           "load_before_after": [round(load0[0], 2), round(os.getloadavg()[0], 2)],
           "cpu": "time.process_time of this process (all threads), encode only (layout + predictor + deflate)",
           "command": " ".join(["python benchmarks/write_throughput.py", *sys.argv[1:]])}
    write_json(RESULTS / "write_throughput_deflate.json", res)
    (RESULTS / "write_throughput_deflate.md").write_text(deflate_markdown(res), encoding="utf-8")
    print(deflate_markdown(res))


def deflate_markdown(res: dict) -> str:
    ok = [r for r in res["rows"] if "skipped" not in r]
    base = next((r for r in ok if r["codec"].startswith("ISA-L 1")), ok[0])
    md = ["# EXR deflate codecs on real frames", "",
          f"`{res['command']}`: {res['files']} EXR frames ({', '.join(res['inputs'])}), each re-encoded by "
          f"room_pipeline.io.exr with every codec ({res['repeats']} repeats); CPU = {res['cpu']}; load "
          f"{res['load_before_after'][0]} -> {res['load_before_after'][1]} (a shared 2-core machine: CPU, not wall).",
          "'same bytes twice' = two encodings in one process gave one file (the cross-process check is "
          "tests/test_exr_writer.py); 'reads back' = OpenImageIO decodes the file to the same pixels.", "",
          "| codec | CPU ms / file | bytes / file | vs ISA-L 1 | same bytes twice | reads back |",
          "| --- | ---: | ---: | ---: | --- | --- |"]
    for r in res["rows"]:
        if "skipped" in r:
            md.append(f"| {r['codec']} | skipped: {r['skipped']} | | | | |")
            continue
        md.append(f"| {r['codec']} | {r['cpu_ms'] / r['files']:.2f} | {r['bytes'] / r['files']:,.0f} | "
                  f"{r['bytes'] / base['bytes']:.3f}x | {r['repeat_identical']} | {r['reads_back_equal']} |")
    return "\n".join(md) + "\n"


if __name__ == "__main__":
    main()
