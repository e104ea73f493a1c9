#!/usr/bin/env python3
"""Parallel executor: render-and-write throughput with 1 and 2 workers (local processes, Ray) and peak memory.

Workload (render-bound, as the render stage): the fast Open3D renderer on the
phantom lumen mesh ``data/output/patient_000/anatomy/lung_model.obj`` with the
camera poses of its first rendered sequence's ``metadata/render.json`` (the catalogue's names) resampled along the
path to N frames (positions linear, rotations slerp), every default modality
(rgb, depth, relative_depth, normals, flow, segmentation) at 600x600, every
file written (PNG / EXR / .flo, atomically) into a temporary folder.  Each
worker builds the renderer once (per-worker state); the exposure is fixed
once before the fan-out.  Thread settings: ``execution.threads_per_worker`` = 1
(each worker's BLAS/OpenMP, OpenImageIO EXR codec, OpenCV and Open3D casts
limited to one thread: the executor's scaling) and 0 (automatic: cores //
workers, i.e. 2 threads for 1 worker, 1 each for 2), plus the in-process
``serial`` backend with every library at its default thread count (what one
worker of the render stage does: the absolute reference).

Each configuration runs in a fresh process (so peak memory is that run's):
wall time of ``map`` over all frames after a warm-up (each worker
initialised; startup reported apart), frames/s, speed-up over 1 worker of
the same backend, CPU seconds of the parent + workers, and peak RSS:
``sampled`` = the largest sum over the driver and its worker processes seen
every 50 ms (psutil), ``hwm`` = the sum of each of those processes' own peak
(VmHWM; an upper bound), and for Ray ``tree`` = the sampled sum over every
process under the driver (Ray's GCS, raylet, agents and idle workers too).

The machine has 2 cores shared with other developers: each run starts once
the others keep at most ``--max-busy`` cores busy (or after ``--max-wait``
seconds), 1- and 2-worker runs alternate ``--repeats`` times (best kept), and
every run records the cores the other users kept busy while it ran (machine
busy time minus this benchmark's processes) and the load average.

    python benchmarks/executor_throughput.py [--frames 50] [--memory-frames 50 500] [--repeats 2] [--quick]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
MODALITIES = ("rgb", "depth", "relative_depth", "normals", "flow", "segmentation")

from room_pipeline.catalog import FOLDERS as _ALL_FOLDERS, SequencePaths, frame_name  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402

PATIENT = PatientPaths(ROOT / "data" / "output", "patient_000")
DATA = PATIENT.root

FOLDERS = {m: _ALL_FOLDERS[m] for m in MODALITIES}
QUICK = "--quick" in sys.argv         # smoke mode: results go to executor_throughput_quick.* (the published ones stay)


def first_sequence() -> SequencePaths:
    """The first rendered sequence of the phantom patient (``<sequence>/metadata/render.json``)."""
    for d in sorted(DATA.iterdir()) if DATA.is_dir() else []:
        if SequencePaths(d).is_rendered():
            return SequencePaths(d)
    raise SystemExit(f"room: error: {DATA}: no rendered sequence (run the default pipeline first)")


# --------------------------------------------------------------------------- workload


def resample_poses(poses: np.ndarray, n: int) -> np.ndarray:
    """``n`` camera-to-world poses evenly along the piecewise path of ``poses`` (linear position, slerp rotation)."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.arange(len(poses), dtype=float)
    slerp = Slerp(t, Rotation.from_matrix(poses[:, :3, :3]))
    s = np.linspace(0.0, t[-1], n)
    out = np.repeat(np.eye(4)[None], n, axis=0)
    out[:, :3, :3] = slerp(s).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(s, t, poses[:, k, 3])
    return out


def build_scene(n: int, exposure_ev: float | None):
    from room_pipeline.anatomy.centreline import CentrelineGraph
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial
    from room_pipeline.render.params import RenderParams
    from room_pipeline.render.sequence import face_labels

    p = RenderParams()
    mesh = read_obj(PATIENT.mesh)
    graph = CentrelineGraph.from_dict(json.loads(PATIENT.centreline_graph.read_text()))
    labels, _ = face_labels(mesh, graph)
    doc = json.loads(first_sequence().render_json.read_text())
    poses = resample_poses(np.array([f["pose"] for f in doc["frames"]]), n)
    cam = CameraIntrinsics.from_fov(600, 600, p.fov_deg, p.near_mm * 1e-3, p.far_mm * 1e-3)
    return Scene(mesh, cam, poses, np.arange(n) / 10.0,
                 material=TissueMaterial(base_color=(0.80, 0.50, 0.54), roughness=p.roughness, specular=p.specular),
                 light=TipLight(power_w=p.light_power_w, radius_m=p.light_radius_mm * 1e-3),
                 film=Film(exposure_ev=exposure_ev, auto_target=0.43), face_labels=labels)


def make_state(out: str, n: int, exposure_ev: float) -> dict:
    """Per-worker state: the renderer (BVH, rays, face tables) built once; Open3D gets the worker's threads."""
    from room_pipeline.execution import worker_threads
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    cfg = RaycastConfig(nthreads=worker_threads() or 0)
    return {"r": RaycastRenderer(build_scene(n, exposure_ev), cfg), "out": Path(out)}


def render_and_write(state: dict, i: int) -> dict:
    """One frame, every default modality, written as the render stage writes it."""
    from room_pipeline.io.images import write_exr, write_flo, write_png8, write_png16

    out, seq = state["r"].render(i, set(MODALITIES)), SequencePaths(state["out"])
    hit = out["hit"]
    write_png8(seq.frame("rgb", i, ".png"), out["rgb"])
    write_exr(seq.frame("depth", i, ".exr"), np.where(hit, out["depth"], 0).astype(np.float32), channels=("Y",),
              attributes={"units": "m", "quantity": "planar z depth, 0 = no hit"})
    write_png16(seq.frame("relative_depth", i, ".png"), out["relative_depth"])
    write_exr(seq.frame("normals", i, ".exr"), out["normals"].astype(np.float32),
              attributes={"frame": "OpenCV camera; R,G,B = x,y,z; unit; 0 = no hit"})
    write_flo(seq.frame("flow", i, ".flo"), out["flow"].astype(np.float32))
    write_png8(seq.folder("flow") / frame_name(i, ".png", "valid"), out["flow_valid"].astype(np.uint8) * 255)
    write_png16(seq.frame("segmentation", i, ".png"), (out["segmentation"] + 1).astype(np.uint16))
    return {"index": i, "hit_fraction": float(hit.mean())}


# --------------------------------------------------------------------------- memory


class MemorySampler:
    """Largest summed RSS of the driver + the given worker pids (and of the driver's whole process tree)."""

    def __init__(self, interval_s: float = 0.05) -> None:
        import psutil

        self.psutil = psutil
        self.me = psutil.Process()
        self.interval = interval_s
        self.worker_pids: set[int] = set()
        self.peak_workers = 0
        self.peak_tree = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _rss(self, p) -> int:
        try:
            return p.memory_info().rss
        except (self.psutil.NoSuchProcess, self.psutil.AccessDenied):
            return 0

    def sample(self) -> None:
        kids = self.me.children(recursive=True)
        own = self._rss(self.me)
        tree = own + sum(self._rss(k) for k in kids)
        workers = own + sum(self._rss(k) for k in kids if k.pid in self.worker_pids)
        self.peak_tree = max(self.peak_tree, tree)
        self.peak_workers = max(self.peak_workers, workers)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.interval)

    def __enter__(self) -> "MemorySampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def vm_hwm(pid: int) -> int:
    """A process's peak resident set (bytes) from /proc/<pid>/status, 0 if unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def busy_seconds() -> float:
    """CPU seconds spent busy by the whole machine (all cores) since boot."""
    import psutil

    t = psutil.cpu_times()
    return t.user + t.nice + t.system + getattr(t, "irq", 0.0) + getattr(t, "softirq", 0.0) + getattr(t, "steal", 0.0)


def wait_until_quiet(max_busy_cores: float, max_wait_s: float) -> float:
    """Wait (up to ``max_wait_s``) until the other users keep at most ``max_busy_cores`` busy; the last reading."""
    import psutil

    t0 = time.monotonic()
    while True:
        busy = psutil.cpu_percent(interval=3.0) / 100.0 * (os.cpu_count() or 1)
        if busy <= max_busy_cores or time.monotonic() - t0 > max_wait_s:
            return busy
        time.sleep(7.0)


def cpu_seconds(pids: list[int]) -> float:
    import psutil

    total = 0.0
    for pid in pids:
        try:
            t = psutil.Process(pid).cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return total


def thread_split(nthreads: int, casts: int = 30) -> dict:
    """CPU ticks per thread of this process over ``casts`` 600x600 casts: does Open3D spread a cast over threads?"""
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    def ticks() -> dict[str, int]:
        out = {}
        for t in os.listdir("/proc/self/task"):
            f = Path(f"/proc/self/task/{t}/stat").read_text().rsplit(")", 1)[1].split()
            out[t] = int(f[11]) + int(f[12])                                    # utime + stime
        return out

    r = RaycastRenderer(build_scene(casts + 1, 0.0), RaycastConfig(nthreads=nthreads))
    r.cast(0)
    before = ticks()
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(1, casts + 1):
        r.cast(i)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    after = ticks()
    busy = sorted((after[t] - before.get(t, 0) for t in after if after[t] - before.get(t, 0) > 0), reverse=True)
    working = [b for b in busy if b >= 0.15 * sum(busy)]          # not the odd tick of a background thread
    return {"open3d_nthreads": nthreads, "threads_doing_work": len(working), "ticks_per_thread": busy,
            "cast_cpu_ms": round(cpu / casts * 1000, 1), "cast_wall_ms": round(wall / casts * 1000, 1)}


# --------------------------------------------------------------------------- one run (own process)


def one_run(backend: str, workers: int, frames: int, tpw: int) -> dict:
    import psutil

    from room_pipeline.execution import ExecutionParams, make_executor
    from room_pipeline.render.raycast import RaycastRenderer

    load0 = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix="room-exec-bench-"))
    try:
        out = tmp / "sequence"
        for f in FOLDERS.values():
            (out / f).mkdir(parents=True)
        t0 = time.perf_counter()
        ev = RaycastRenderer(build_scene(frames, None), ).exposure_ev      # once, before the fan-out
        t_exposure = time.perf_counter() - t0
        params = ExecutionParams(backend=backend, workers=workers, threads_per_worker=tpw)
        init = (make_state, (str(out), frames, ev))
        with MemorySampler() as mem, make_executor(params, init=init) as ex:
            t0 = time.perf_counter()
            ex.map(render_and_write, list(range(min(workers, frames))), desc="warm-up")   # start + init workers
            t_start = time.perf_counter() - t0
            if backend == "ray":
                pids = ex.actor_pids()
            elif backend == "serial":
                pids = []
            else:
                pids = [c.pid for c in psutil.Process().children() if c.pid != os.getpid()
                        and "resource_tracker" not in " ".join(c.cmdline())]
            mem.worker_pids = set(pids)
            tree = [os.getpid()] + [c.pid for c in psutil.Process().children(recursive=True)]
            cpu0, tree0, sys0 = cpu_seconds([os.getpid(), *pids]), cpu_seconds(tree), busy_seconds()
            t0 = time.perf_counter()
            recs = ex.map(render_and_write, range(frames), desc="frames")
            wall = time.perf_counter() - t0
            cpu = cpu_seconds([os.getpid(), *pids]) - cpu0
            others = (busy_seconds() - sys0) - (cpu_seconds(tree) - tree0)
            mem.sample()
            hwm = vm_hwm(os.getpid()) + sum(vm_hwm(p) for p in pids)
        n_files = sum(1 for _ in out.rglob("*") if _.is_file())
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load1 = os.getloadavg()
    return {"backend": backend, "workers": workers, "frames": frames, "threads_per_worker": tpw,
            "threads": "all (library defaults)" if backend == "serial" else params.threads,
            "wall_s": round(wall, 3), "frames_per_s": round(frames / wall, 3), "startup_s": round(t_start, 3),
            "exposure_s": round(t_exposure, 3), "cpu_s": round(cpu, 2), "cpu_s_per_frame": round(cpu / frames, 4),
            "other_users_cores_busy": round(max(others, 0.0) / wall, 2),
            "peak_rss_mb_sampled": round(mem.peak_workers / 2**20, 1), "peak_rss_mb_hwm": round(hwm / 2**20, 1),
            "peak_rss_mb_tree": round(mem.peak_tree / 2**20, 1), "worker_pids": len(pids),
            "files": n_files, "bytes_written": size, "hit_fraction_mean": round(float(np.mean(
                [r["hit_fraction"] for r in recs])), 4),
            "loadavg_start": [round(x, 2) for x in load0], "loadavg_end": [round(x, 2) for x in load1]}


def run_isolated(backend: str, workers: int, frames: int, tpw: int, max_busy: float, max_wait: float) -> dict:
    """``one_run`` in a fresh interpreter, started once the other users leave the machine quiet enough."""
    busy = wait_until_quiet(max_busy, max_wait)
    cmd = [sys.executable, __file__, "--one", backend, str(workers), str(frames), str(tpw)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} failed:\n{res.stderr[-3000:]}")
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    doc["busy_cores_before"] = round(busy, 2)
    print(f"  {backend:6s} workers={workers} frames={frames:4d} threads_per_worker={tpw}: "
          f"{doc['frames_per_s']:6.2f} frames/s, cpu {doc['cpu_s_per_frame'] * 1000:5.0f} ms/frame, "
          f"peak {doc['peak_rss_mb_sampled']:7.1f} MB (hwm {doc['peak_rss_mb_hwm']:.0f}), "
          f"others busy {busy:.2f} before / {doc['other_users_cores_busy']:.2f} during, "
          f"load {doc['loadavg_start'][0]:.2f} -> {doc['loadavg_end'][0]:.2f}", flush=True)
    return doc


# --------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--one", nargs=4, metavar=("BACKEND", "WORKERS", "FRAMES", "THREADS_PER_WORKER"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--thread-split", type=int, metavar="NTHREADS", help=argparse.SUPPRESS)
    ap.add_argument("--reuse-runs", action="store_true",
                    help="keep the runs of the existing results JSON; only re-measure the thread split and rewrite")
    ap.add_argument("--frames", type=int, default=50, help="frames of the throughput runs")
    ap.add_argument("--memory-frames", type=int, nargs="*", default=[50, 500])
    ap.add_argument("--repeats", type=int, default=2, help="1- and 2-worker runs alternate this many times; best kept")
    ap.add_argument("--max-busy", type=float, default=0.3,
                    help="start a run once other users keep at most this many cores busy ...")
    ap.add_argument("--max-wait", type=float, default=180, help="... or after this many seconds of waiting")
    ap.add_argument("--quick", action="store_true", help="10 frames, local only, no memory runs (smoke test)")
    args = ap.parse_args()
    if args.one:
        b, w, f, t = args.one
        print(json.dumps(one_run(b, int(w), int(f), int(t))))
        return
    if args.thread_split is not None:
        print(json.dumps(thread_split(args.thread_split)))
        return
    if args.quick:
        args.frames, args.memory_frames = 10, []
    backends = ["local"] if args.quick else ["local", "ray"]
    threads = []
    for nthreads in (1, 0):                       # in fresh processes: Open3D's thread pool is per process
        res = subprocess.run([sys.executable, __file__, "--thread-split", str(nthreads)], capture_output=True,
                             text=True, check=True)
        threads.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(f"  Open3D nthreads={nthreads}: {threads[-1]}", flush=True)
    if args.reuse_runs:
        old = json.loads((RESULTS / "executor_throughput.json").read_text())
        old.update(threads=threads, thread_split_measured=time.strftime("%Y-%m-%d %H:%M"),
                   report_command=" ".join(["python", "benchmarks/executor_throughput.py", *sys.argv[1:]]))
        write_results(old)
        return
    started = time.strftime("%Y-%m-%d %H:%M")
    print(f"load average at start: {os.getloadavg()}", flush=True)
    runs, all_runs = [], []
    tries_serial = [run_isolated("serial", 1, args.frames, 0, args.max_busy, args.max_wait)
                    for _ in range(args.repeats)]
    all_runs += tries_serial
    best = max(tries_serial, key=lambda d: d["frames_per_s"])
    best["repeats"] = len(tries_serial)
    runs.append(best)
    for tpw in (1, 0):
        for backend in backends:
            tries: dict[int, list] = {1: [], 2: []}
            for _ in range(args.repeats):
                for workers in (1, 2):
                    doc = run_isolated(backend, workers, args.frames, tpw, args.max_busy, args.max_wait)
                    tries[workers].append(doc)
                    all_runs.append(doc)
            for workers in (1, 2):
                best = max(tries[workers], key=lambda d: d["frames_per_s"])
                best["repeats"] = len(tries[workers])
                runs.append(best)
    memory = []
    for backend in backends:
        for frames in args.memory_frames:
            memory.append(run_isolated(backend, 2, frames, 1, args.max_busy, args.max_wait))
    doc = {"command": " ".join(["python", "benchmarks/executor_throughput.py", *sys.argv[1:]]),
           "started": started, "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                                           "note": "shared with other jobs"},
           "workload": {"mesh": str(PATIENT.mesh.relative_to(ROOT)),
                        "poses": f"{first_sequence().render_json.relative_to(DATA)} resampled (linear + slerp)",
                        "size": [600, 600], "modalities": list(MODALITIES)},
           "selection": f"best of {args.repeats} alternating runs per row; each run started once other users kept "
                        f"<= {args.max_busy} cores busy (3 s sample) or after {args.max_wait:.0f} s of waiting",
           "runs": runs, "all_runs": all_runs, "memory": memory, "threads": threads,
           "thread_split_measured": time.strftime("%Y-%m-%d %H:%M")}
    write_results(doc)


def write_results(doc: dict) -> None:
    """Derived numbers, then the JSON and the Markdown report."""
    from room_pipeline.io.atomic import write_json, write_text

    speedups, cpu_bound, vs_serial = {}, {}, {}
    serial = next((r for r in doc["runs"] if r["backend"] == "serial"), None)
    for tpw in (1, 0):
        for backend in sorted({r["backend"] for r in doc["runs"]} - {"serial"}):
            sel = [r for r in doc["runs"] if (r["backend"], r["threads_per_worker"]) == (backend, tpw)]
            one = next(r for r in sel if r["workers"] == 1)
            two = next(r for r in sel if r["workers"] == 2)
            key = f"{backend}_tpw{tpw}"
            speedups[key] = round(two["frames_per_s"] / one["frames_per_s"], 3)
            # what two idle cores would give if each worker kept its CPU time per frame (no shared bottleneck)
            cpu_bound[key] = round(2 * one["cpu_s_per_frame"] / two["cpu_s_per_frame"], 3)
            if serial:
                vs_serial[key] = round(two["frames_per_s"] / serial["frames_per_s"], 3)
    doc["speedup_2_over_1"] = speedups
    doc["speedup_bound_from_cpu_time"] = cpu_bound
    doc["speedup_2_workers_over_serial"] = vs_serial
    stem = "executor_throughput_quick" if QUICK else "executor_throughput"
    write_json(RESULTS / f"{stem}.json", doc)
    write_text(RESULTS / f"{stem}.md", to_markdown(doc))
    for name in (f"{stem}.json", f"{stem}.md"):
        os.chmod(RESULTS / name, 0o644)          # the atomic writer's temporary files are 0600
    print(json.dumps({"speedup_2_over_1": speedups, "speedup_bound_from_cpu_time": cpu_bound,
                      "speedup_2_workers_over_serial": vs_serial}))


def to_markdown(doc: dict) -> str:
    md = ["# Parallel executor: render-and-write throughput and memory", "",
          f"Command: `{doc['command']}` ({doc['started']})"
          + (f"; thread split and this report: `{doc['report_command']}`" if doc.get("report_command") else "")
          + f".  Machine: {doc['machine']['cpus']} cores, "
          f"{doc['machine']['note']}: {doc['selection']}.  'others busy' = cores kept busy by other users' "
          "processes during the run (machine busy time minus this benchmark's processes), with the 1-minute load "
          "average at start -> end.", "",
          "Workload: fast Open3D renderer on the phantom mesh, 600x600, all default modalities "
          f"({', '.join(doc['workload']['modalities'])}), every file written; per-worker state = the renderer "
          "(built once per worker); each configuration in a fresh process; time of `map` over all frames after "
          "a warm-up map that starts and initialises the workers (startup listed apart).  Threads per worker = "
          "`execution.threads_per_worker` (BLAS/OpenMP, OpenImageIO EXR codec, OpenCV, Open3D casts; 0 = cores // "
          "workers); `serial` = in this process, every library at its default thread count.", "",
          "| backend | workers | threads per worker | frames | frames/s | speed-up 2/1 | vs serial | startup s | "
          "CPU ms/frame | cores used | peak RSS MB (driver+workers) | others busy (cores) | load start -> end |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    serial = next((r for r in doc["runs"] if r["backend"] == "serial"), None)
    for r in doc["runs"]:
        key = f"{r['backend']}_tpw{r['threads_per_worker']}"
        sp = doc["speedup_2_over_1"].get(key) if r["workers"] == 2 else (None if r["backend"] == "serial" else 1.0)
        vs = r["frames_per_s"] / serial["frames_per_s"] if serial else None
        thr = r["threads"] if r["backend"] != "serial" else "all"
        if r["backend"] != "serial" and r["threads_per_worker"] == 0:
            thr = f"auto ({r['threads']})"
        md.append(f"| {r['backend']} | {r['workers']} | {thr} | {r['frames']} | {r['frames_per_s']:.2f} | "
                  f"{'-' if sp is None else f'{sp:.2f}'} | {'-' if vs is None else f'{vs:.2f}'} | "
                  f"{r['startup_s']:.1f} | {r['cpu_s_per_frame'] * 1000:.0f} | "
                  f"{r['frames_per_s'] * r['cpu_s_per_frame']:.2f} | "
                  f"{r['peak_rss_mb_sampled']:.0f} | {r['other_users_cores_busy']:.2f} | "
                  f"{r['loadavg_start'][0]:.2f} -> {r['loadavg_end'][0]:.2f} |")
    others = [r["other_users_cores_busy"] for r in doc["runs"]]
    md += ["", "Speed-up 2/1 = frames/s with 2 workers / with 1 (same backend and thread setting); vs serial = "
           "frames/s / the serial row's.  'cores used' = frames/s x CPU s per frame (driver + workers).  The other "
           f"users kept {min(others):.2f}-{max(others):.2f} of the 2 cores busy during these runs.  "
           "With one thread per worker one worker uses about one core, so the second worker has a core of its "
           "own: that is the executor's scaling.  With automatic threads one worker already spreads over both "
           "cores (its libraries' thread pools), so a second worker adds less; the 'vs serial' column is what "
           "a user gains over the single in-process worker.  Bound from CPU time (2 x CPU(1 worker) / CPU(2 "
           "workers), if nothing were shared): "
           + ", ".join(f"{k.replace('_tpw1', ', 1 thread/worker').replace('_tpw0', ', auto threads')} {v:.2f}"
                       for k, v in doc["speedup_bound_from_cpu_time"].items()) + "."]
    if doc.get("threads"):
        t1 = next(t for t in doc["threads"] if t["open3d_nthreads"] == 1)
        t0 = next(t for t in doc["threads"] if t["open3d_nthreads"] == 0)
        md += ["", f"Open3D threads (measured {doc.get('thread_split_measured', '')}, 30 casts of 600x600 rays in "
               "one process, CPU ticks per thread): with `nthreads=1` the cast runs on "
               f"{t1['threads_doing_work']} thread(s) (ticks {t1['ticks_per_thread']}); with the default "
               f"`nthreads=0` on {t0['threads_doing_work']} (ticks {t0['ticks_per_thread']}).  CPU per cast "
               f"{t1['cast_cpu_ms']} ms vs {t0['cast_cpu_ms']} ms."]
    if doc["memory"]:
        md += ["", "## Peak memory vs number of frames (2 workers, 1 thread per worker)", "",
               "| backend | frames | frames/s | peak RSS MB sampled (driver+workers) | sum of per-process peaks MB | "
               "whole process tree MB | GB written | others busy (cores) | load start -> end |",
               "|---|---|---|---|---|---|---|---|---|"]
        for r in doc["memory"]:
            md.append(f"| {r['backend']} | {r['frames']} | {r['frames_per_s']:.2f} | {r['peak_rss_mb_sampled']:.0f} "
                      f"| {r['peak_rss_mb_hwm']:.0f} | {r['peak_rss_mb_tree']:.0f} | {r['bytes_written'] / 1e9:.2f} | "
                      f"{r['other_users_cores_busy']:.2f} | {r['loadavg_start'][0]:.2f} -> {r['loadavg_end'][0]:.2f} |")
    return "\n".join(md) + "\n"


if __name__ == "__main__":
    main()
