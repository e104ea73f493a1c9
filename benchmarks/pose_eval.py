#!/usr/bin/env python3
"""Pose evaluation (stage `evaluate_pose`): wall time and accuracy of COLMAP and ORB VO on a 100-frame sequence.

Target (issue #7): evaluating a 100-frame sequence takes < 2 minutes on this machine.

The sequence is rendered here, into a temporary folder with the render stage's
layout (``rgb/``, ``calibration/camera_params.json``, ``metadata/render.json``),
by the fast renderer (Open3D ray casting) through the Python API: the phantom
lumen mesh and the first planned trajectory of the pipeline's patient_000
(``data/output/patient_000/anatomy/lung_model.obj`` and
``sequence_000/metadata/trajectory.json`` when present; ``--obj`` /
``--trajectory`` choose others), consecutive poses from ``--start``, 600x600
pixels, 85 deg.  Two variants of the same frames:

* ``plain``    -- the renderer's shading as the pipeline writes it (smooth, no
                 mucosal texture: the hard case of the paper);
* ``textured`` -- the same radiance multiplied by a procedural 3D texture fixed
                 to the surface (sum of random plane waves of 0.6-4 mm
                 wavelength evaluated at each hit point), so that feature-based
                 methods have something to match.

Each variant is evaluated by ``room_pipeline.stages.evaluate_pose.run`` (PNG
loading, downscaling, every method, metrics, files) under a grid of knobs
(downscale factor, COLMAP sequential-matching overlap, SIFT features).  Wall
time on a shared 2-core machine depends on the other users' load (reported:
load average before and after); CPU time of this process is reported too.

    python benchmarks/pose_eval.py [--frames 100] [--start 100] [--quick]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from room_pipeline.io.atomic import write_json, write_text
from room_pipeline.io.images import write_png8
from room_pipeline.io.mesh import read_obj
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import RaycastRenderer
from room_pipeline.render.scene import Scene
from room_pipeline.render.shading import linear_to_srgb8
from room_pipeline.stages import evaluate_pose

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PATIENT = ROOT / "data" / "output" / "patient_000"
MM = 1e-3

#: (label, evaluate.pose overrides)
GRID = [
    ("full-res, overlap 10", {"downscale": 1.0, "colmap": {"overlap": 10}}),
    ("downscale 2, overlap 10", {"downscale": 2.0, "colmap": {"overlap": 10}}),
    ("downscale 2, overlap 5", {"downscale": 2.0, "colmap": {"overlap": 5}}),          # the conf defaults
    ("downscale 3, overlap 5", {"downscale": 3.0, "colmap": {"overlap": 5}}),
]


def solid_texture(points: np.ndarray, seed: int = 0, n: int = 32, wavelengths=(0.6 * MM, 4 * MM)) -> np.ndarray:
    """Albedo factor in [0.2, 1] of a 3D texture fixed to the surface: a sum of random plane waves."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    f = 1.0 / rng.uniform(*wavelengths, size=n)
    phase = rng.uniform(0, 2 * np.pi, n)
    v = np.sin(2 * np.pi * points @ (d * f[:, None]).T + phase).sum(-1) / math.sqrt(n / 2)
    return 0.2 + 0.8 / (1.0 + np.exp(-2.5 * v))


def inputs(args) -> tuple:
    """Mesh, camera-to-world poses (frames start .. start+frames-1) and a description."""
    obj = Path(args.obj or PATIENT / "anatomy" / "lung_model.obj")
    traj = Path(args.trajectory or PATIENT / "sequence_000" / "metadata" / "trajectory.json")
    if obj.is_file() and traj.is_file():
        mesh = read_obj(obj)
        poses = np.array([f["pose"] for f in json.loads(traj.read_text())["frames"]])
        src = {"mesh": str(obj.relative_to(ROOT) if obj.is_relative_to(ROOT) else obj),
               "trajectory": str(traj.relative_to(ROOT) if traj.is_relative_to(ROOT) else traj)}
    else:   # regenerate through the API (as benchmarks/raycast_renderer.py does)
        from room_pipeline.anatomy.centreline import from_airway_tree
        from room_pipeline.anatomy.mesh import MeshParams, extract_surface
        from room_pipeline.anatomy.phantom import PhantomParams, make_phantom
        from room_pipeline.planning.trajectory import TrajectoryParams, as_sdf_fn, plan_path, select_targets

        ph = make_phantom(PhantomParams(spacing_mm=1.0, max_generation=6), seed=0)
        mesh = extract_surface(ph.sdf, MeshParams()).mesh
        graph = from_airway_tree(ph.tree, 1e-3)
        tp = TrajectoryParams(targets="leaves", max_generation=3, unreachable="nearest")
        poses = plan_path(graph, select_targets(graph, tp)[0], as_sdf_fn(ph.tree), tp).poses
        src = {"mesh": "phantom seed 0, 1 mm, generations <= 6 (regenerated)", "trajectory": "first leaf, gen 3"}
    start = min(args.start, max(0, len(poses) - args.frames))
    sel = poses[start:start + args.frames]
    step = np.linalg.norm(np.diff(sel[:, :3, 3], axis=0), axis=1)
    src.update({"frames": [start, start + len(sel) - 1], "step_mm_mean": round(float(step.mean()) * 1e3, 4)})
    return mesh, sel, src


def render(mesh, poses, cam, root: Path) -> dict:
    """Write both variants in the render stage's layout under root/<variant>/p0/sequence_000; return timings."""
    r = RaycastRenderer(Scene(mesh, cam, poses, np.arange(len(poses)) * 0.1))
    t0 = time.perf_counter()
    frames = []
    for i in range(len(poses)):
        o = r.render(i, {"rgb", "world_points"})
        lin = o["rgb_linear"]
        tex = lin * solid_texture(o["world_points"])[..., None].astype(np.float32)
        for variant, im in (("plain", o["rgb"]), ("textured", linear_to_srgb8(tex, 0.0))):
            write_png8(root / variant / "p0" / "sequence_000" / "rgb" / f"frame_{i:04d}.png", im)
        frames.append({"index": i, "source_index": i, "timestamp": 0.1 * i, "pose": poses[i].tolist()})
    for variant in ("plain", "textured"):
        seq = root / variant / "p0" / "sequence_000"
        write_json(seq / "calibration" / "camera_params.json", cam.to_dict())
        write_json(seq / "metadata" / "render.json", {"frames": frames})
    return {"render_and_write_s": round(time.perf_counter() - t0, 2), "exposure_ev": r.exposure_ev}


def evaluate(root: Path, variant: str, overrides: dict) -> dict:
    pose = OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "evaluate" / "default.yaml"))["pose"]
    pose["methods"] = ["colmap", "orb_vo"]
    pose["max_frames"] = None
    for k, v in overrides.items():
        if isinstance(v, dict):
            pose[k] = {**pose[k], **v}
        else:
            pose[k] = v
    cfg = OmegaConf.create({"output_dir": str(root / variant), "evaluate": {"pose": pose}})
    w0, c0 = time.perf_counter(), time.process_time()
    evaluate_pose.run(cfg, "p0/sequence_000")
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    doc = json.loads((root / variant / "p0" / "sequence_000" / "evaluation" / "pose.json").read_text())
    out = {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "image_size": doc["input"]["image_size"], "methods": {}}
    for name, r in doc["methods"].items():
        out["methods"][name] = {k: r.get(k) for k in ("RRA@5", "RTA@5", "AUC@30", "registration_rate",
                                                      "ate_rmse_mm", "rotation_error_median_deg",
                                                      "translation_error_median_deg", "seconds", "n_registered")}
        info = r.get("info") or {}
        out["methods"][name]["info"] = {k: info[k] for k in ("error", "points3D", "reconstructions", "steps",
                                                             "median_keypoints") if k in info}
    return out


def pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def num(v, d=2) -> str:
    return "-" if v is None else f"{v:.{d}f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--start", type=int, default=100, help="first trajectory pose used")
    ap.add_argument("--size", type=int, default=600)
    ap.add_argument("--obj")
    ap.add_argument("--trajectory")
    ap.add_argument("--quick", action="store_true", help="only the default knobs (downscale 2, overlap 5)")
    ap.add_argument("--report-only", action="store_true", help="rewrite the .md from the saved .json")
    args = ap.parse_args()
    if args.report_only:
        write_text(RESULTS / "pose_eval.md", report(json.loads((RESULTS / "pose_eval.json").read_text())))
        return
    load0 = os.getloadavg()
    mesh, poses, src = inputs(args)
    cam = CameraIntrinsics.from_fov(args.size, args.size, 85.0)
    grid = [g for g in GRID if g[0] == "downscale 2, overlap 5"] if args.quick else GRID
    results = {"command": "python benchmarks/pose_eval.py" + (" --quick" if args.quick else "")
               + (f" --frames {args.frames}" if args.frames != 100 else ""),
               "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version(),
                           "load_average_before": [round(x, 2) for x in load0]},
               "sequence": {**src, "n_frames": len(poses), "image": [args.size, args.size], "fov_deg": 85.0},
               "target_s": 120.0, "runs": []}
    with tempfile.TemporaryDirectory(prefix="room_pose_bench_") as tmp:
        root = Path(tmp)
        results["render"] = render(mesh, poses, cam, root)
        print(f"rendered {len(poses)} frames x 2 variants in {results['render']['render_and_write_s']} s", flush=True)
        for variant in ("plain", "textured"):
            for label, ov in grid:
                r = evaluate(root, variant, ov)
                r.update({"variant": variant, "knobs": label, "overrides": ov})
                results["runs"].append(r)
                c, o = r["methods"]["colmap"], r["methods"]["orb_vo"]
                print(f"{variant:8s} {label:26s} wall {r['wall_s']:6.1f} s  colmap {c['seconds']:.1f} s "
                      f"reg {c['n_registered']} AUC {pct(c['AUC@30'])}  orb {o['seconds']:.1f} s "
                      f"reg {o['n_registered']} AUC {pct(o['AUC@30'])}", flush=True)
    results["machine"]["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "pose_eval.json", results)
    write_text(RESULTS / "pose_eval.md", report(results))
    print(report(results))


def report(res: dict) -> str:
    s, m = res["sequence"], res["machine"]
    lines = [
        "# Pose evaluation speed and accuracy (stage `evaluate_pose`)", "",
        f"Command: `{res['command']}`.  Machine: {m['platform']}, {m['cpus']} CPUs shared with other developers' "
        f"jobs; load average {m['load_average_before'][0]} before, {m['load_average_after'][0]} after.  "
        "Single-threaded COLMAP (num_threads 1, deterministic).",
        "",
        f"Sequence: {s['n_frames']} consecutive frames (trajectory poses {s['frames'][0]}..{s['frames'][1]}, "
        f"mean step {s['step_mm_mean']} mm) of `{s['trajectory']}` through `{s['mesh']}`, rendered "
        f"{s['image'][0]}x{s['image'][1]} px, {s['fov_deg']} deg, by the fast renderer "
        f"({res['render']['render_and_write_s']} s for both variants incl. PNG writing).  `plain`: the pipeline's "
        "shading; `textured`: the same with a procedural 3D texture fixed to the surface.",
        "",
        "Wall = the whole stage (`evaluate_pose.run`: PNG loading, downscaling, both methods, metrics, files); "
        f"target < {res['target_s']:.0f} s.  Scores over all {s['n_frames'] * (s['n_frames'] - 1) // 2} frame "
        "pairs, in %; ATE in mm after Sim(3) alignment; '-' = undefined (nothing registered).",
        "",
        "| variant | knobs | image px | wall s | CPU s | method | time s | registered | RRA@5 | RTA@5 | AUC@30 "
        "| ATE mm | median rot err deg | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["runs"]:
        for name, x in r["methods"].items():
            note = x["info"].get("error") or (f"{x['info'].get('reconstructions')} models, "
                                              f"{x['info'].get('points3D')} points" if name == "colmap" else
                                              f"median {x['info'].get('median_keypoints')} keypoints")
            lines.append(f"| {r['variant']} | {r['knobs']} | {r['image_size'][0]} | {r['wall_s']} | {r['cpu_s']} | "
                         f"{name} | {num(x['seconds'], 1)} | {x['n_registered']}/{s['n_frames']} | "
                         f"{pct(x['RRA@5'])} | {pct(x['RTA@5'])} | {pct(x['AUC@30'])} | {num(x['ate_rmse_mm'], 3)} | "
                         f"{num(x['rotation_error_median_deg'])} | {note} |")
    lines += ["", "## Against the target (textured: the variant where COLMAP registers; the plain frames fail "
              "fast)", "", "| knobs | wall s | CPU s | < 120 s wall | < 120 s CPU | COLMAP AUC@30 | ORB VO AUC@30 |",
              "|---|---|---|---|---|---|---|"]
    for r in res["runs"]:
        if r["variant"] != "textured":
            continue
        c, o = r["methods"]["colmap"], r["methods"]["orb_vo"]
        ok_wall = "yes" if r["wall_s"] < res["target_s"] else "no"
        ok_cpu = "yes" if r["cpu_s"] < res["target_s"] else "no"
        lines.append(f"| {r['knobs']} | {r['wall_s']} | {r['cpu_s']} | {ok_wall} | {ok_cpu} | {pct(c['AUC@30'])} | "
                     f"{pct(o['AUC@30'])} |")
    lines += ["", "CPU s is this process's CPU time: about what the wall time would be on an otherwise idle core "
              "(COLMAP runs single-threaded); the wall times above are inflated by the other users' jobs (load "
              "average well above the 2 cores).  COLMAP's cost is SIFT extraction (grows with the pixel count) plus "
              "brute-force matching of every frame with the next `overlap` frames (grows with overlap x "
              "features^2); ORB VO takes seconds.  Defaults in conf/evaluate/default.yaml: downscale 2 (600 -> 300 "
              "px) and overlap 5 -- the same COLMAP accuracy as full resolution / overlap 10 on this sequence for "
              "about a third of the CPU time; downscale 3 is faster still for COLMAP but costs ORB VO 36 points of "
              "RRA@5."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
