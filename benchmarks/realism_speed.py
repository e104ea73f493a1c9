#!/usr/bin/env python3
"""Cost and error of the fast renderer's appearance knobs at 600x600 (the default RGB).

    python benchmarks/realism_speed.py [--inputs DIR] [--frames 10]

Inputs: an output_dir with ``patient_000/anatomy/{lung_model.obj,centreline_graph.json}`` and
``patient_000/sequence_000/metadata/simulation.json`` (``room run --until simulate output_dir=DIR``).
Scene = the render stage's defaults (composed ``conf/``), ``--frames`` poses evenly spaced over the
sequence, one fixed exposure per frame (from the per-frame meter).  For each setting: CPU seconds per
frame of the RGB (cast + normals + appearance + shading; ``time.process_time``, the process's user+sys,
so other users' load does not count) and wall seconds, and PSNR of the 8-bit RGB against the
per-pixel, stride-1 reference (every pixel evaluates the full appearance function).  Also the cost of
the exposure meter pre-pass per frame.  Results: benchmarks/results/realism_speed.{json,md}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
RESULTS = ROOT / "benchmarks" / "results"


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output"))
    ap.add_argument("--frames", type=int, default=10)
    a = ap.parse_args()
    from room_pipeline.anatomy.centreline import CentrelineGraph
    from room_pipeline.config.compose import compose
    from room_pipeline.conventions import MM
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.exposure import exposure_track
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
    from room_pipeline.render.scene import Scene
    from room_pipeline.render.texture import airway_coordinates
    from room_pipeline.render.params import RenderParams, exposure_params, scene_parts
    from room_pipeline.render.sequence import face_labels

    pat = Path(a.inputs) / "patient_000"
    p = RenderParams.from_dict(compose([]).render)
    from room_pipeline.paths import PatientPaths

    pp = PatientPaths(pat.parent, pat.name)
    mesh = read_obj(pp.mesh)
    graph = CentrelineGraph.from_dict(json.loads(pp.centreline_graph.read_text()))
    sim = json.loads(pp.seq("sequence_000").simulation.read_text())
    poses_all = np.array([f["tip_pose"] for f in sim["frames"]])
    idx = np.linspace(0, len(poses_all) - 1, a.frames).round().astype(int)
    cam = CameraIntrinsics.from_fov(p.width, p.height, p.fov_deg, p.near_mm * MM, p.far_mm * MM)
    material, light, film = scene_parts(p)
    t0 = time.process_time()
    air = airway_coordinates(mesh.vertices, graph)
    t_air = time.process_time() - t0
    labels, _ = face_labels(mesh, graph)
    sc = Scene(mesh, cam, poses_all[idx], np.arange(len(idx)) * 10.0, material=material, light=light, film=film,
               face_labels=labels, vertex_airway=air)
    c0, w0 = time.process_time(), time.perf_counter()
    evs = exposure_track(sc, exposure_params(p))
    meter_cpu = (time.process_time() - c0) / len(idx)
    meter_wall = (time.perf_counter() - w0) / len(idx)
    sc = dataclasses.replace(sc, film=dataclasses.replace(film, frame_ev=evs))
    settings = [("per-pixel, stride 1 (reference)", RaycastConfig(shading_stride=1)),
                ("per-pixel, stride 2 (default)", RaycastConfig(shading_stride=2)),
                ("per-pixel, stride 4", RaycastConfig(shading_stride=4)),
                ("vertex bake (what Cycles reads)", RaycastConfig(per_pixel_texture=False))]
    ref, rows = None, []
    load0 = os.getloadavg()[0]
    for name, cfg in settings:
        r = RaycastRenderer(sc, cfg)
        imgs, cpu, wall = [], 0.0, 0.0
        for i in range(len(idx)):
            c0, w0 = time.process_time(), time.perf_counter()
            imgs.append(r.render(i, {"rgb"})["rgb"])
            cpu += time.process_time() - c0
            wall += time.perf_counter() - w0
        if ref is None:
            ref = imgs
        ps = [psnr(x, y) for x, y in zip(imgs, ref)]
        rows.append({"setting": name, "cpu_s_per_frame": round(cpu / len(idx), 3),
                     "wall_s_per_frame": round(wall / len(idx), 3),
                     "psnr_db_vs_reference_mean": round(float(np.mean(ps)), 2) if ref is not imgs else None,
                     "psnr_db_vs_reference_min": round(float(np.min(ps)), 2) if ref is not imgs else None})
        print(json.dumps(rows[-1]), flush=True)
    res = {"frames": len(idx), "resolution": [p.width, p.height], "rows": rows,
           "meter_cpu_s_per_frame": round(meter_cpu, 4), "meter_wall_s_per_frame": round(meter_wall, 4),
           "airway_coordinates_cpu_s": round(t_air, 3), "mesh_vertices": int(mesh.n_vertices),
           "load_avg": [round(load0, 1), round(os.getloadavg()[0], 1)], "cores": os.cpu_count()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "realism_speed.json").write_text(json.dumps(res, indent=1))
    md = ["# Fast renderer: appearance knobs, cost vs error (600x600 RGB)", "",
          f"`python benchmarks/realism_speed.py --frames {len(idx)}`: default phantom patient_000/sequence_000, "
          f"{len(idx)} poses evenly spaced, the render stage's default scene; RGB only (cast, normals, appearance, "
          f"shading, response). CPU = user+sys of this process; load average {res['load_avg'][0]} -> "
          f"{res['load_avg'][1]} on {res['cores']} cores (wall times include other users' jobs).", "",
          "| setting | CPU s/frame | wall s/frame | PSNR vs stride 1, mean (min) dB |", "|---|---|---|---|"]
    for r_ in rows:
        ps = "reference" if r_["psnr_db_vs_reference_mean"] is None else \
            f"{r_['psnr_db_vs_reference_mean']} ({r_['psnr_db_vs_reference_min']})"
        md.append(f"| {r_['setting']} | {r_['cpu_s_per_frame']} | {r_['wall_s_per_frame']} | {ps} |")
    md += ["", f"Exposure meter pre-pass (75x75 cast + shade, sequential in the driver): {res['meter_cpu_s_per_frame']} "
               f"CPU s/frame. Airway coordinates of the {res['mesh_vertices']} vertices (once per sequence): "
               f"{res['airway_coordinates_cpu_s']} CPU s."]
    (RESULTS / "realism_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
