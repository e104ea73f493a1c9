"""Collision surface vs simulate speed and tip poses (issues #17, #18): faces, error bound, CPU time, tip difference.

    .venv/bin/python benchmarks/collision_speed.py RUN_DIR[:SEQUENCE] ... [--bounds 0.25,0.1,0.05]
        [--fractions 0.25] [--repeats 2] [--name collision_speed]

Each RUN_DIR is a patient folder written by the pipeline up to the trajectory stage (e.g.
``room run patients=shared_masks --patient atm_001 --until trajectory output_dir=/tmp/x`` -> /tmp/x/atm_001,
or ``room run patients=phantom_single --until trajectory output_dir=/tmp/p`` -> /tmp/p/patient_000).
The reference wall is the render mesh (``anatomy/lung_model.obj``, the lumen surface every image is
rendered from), whole, at full resolution.  For every (fraction, bound) a collision surface is made from the
closed render mesh with the mesh stage's routine (``anatomy/decimate.py``, as ``mesh.collision_decimation`` /
``mesh.collision_max_error_mm``), and the simulate stage's run (default config: the route's corridor, the
entrance opened as the stage does) is repeated on it.  Reported per surface: faces; the measured one-sided
distances both ways to the render mesh (max, and p95 of both) in mm; CPU time of the decimation; simulate
CPU time (time.process_time of the call, user+sys; the minimum of ``--repeats`` runs) and x real time; the
tip position / view direction difference to the run on the render mesh (all frames).  Bullet's own noise
floor: the render mesh with its triangles in reverse order (the same surface) against the render mesh.
The load average is recorded (wall time is shared with other jobs; CPU time is the figure).
Writes benchmarks/results/NAME.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from collision_corridor import angle_deg, inputs  # noqa: E402
from room_pipeline.io.mesh import read_obj  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402
from room_pipeline.robot.sequence_sim import open_entrance  # noqa: E402
from room_pipeline.anatomy.collision import collision_surface  # noqa: E402
from room_pipeline.anatomy.decimate import two_sided_error  # noqa: E402
from room_pipeline.io.mesh import Mesh  # noqa: E402
from room_pipeline.robot.kinematics import ScopeGeometry  # noqa: E402
from room_pipeline.robot.sim_params import SimParams  # noqa: E402
from room_pipeline.robot.simulation import simulate  # noqa: E402


def sim(traj, mesh: Mesh, repeats: int):
    best, res = None, None
    for _ in range(max(1, repeats)):
        c0, w0 = time.process_time(), time.perf_counter()
        r = simulate(traj, mesh, SimParams(), ScopeGeometry())
        c, w = time.process_time() - c0, time.perf_counter() - w0
        if best is None or c < best[0]:
            best = (c, w)
        res = r
    return res, best[0], best[1]


def diff(a, b) -> dict:
    dp = np.linalg.norm(a.tip_poses[:, :3, 3] - b.tip_poses[:, :3, 3], axis=1) * 1e3
    dv = angle_deg(a.tip_poses[:, :3, 2], b.tip_poses[:, :3, 2])
    return {"tip_max_mm": float(dp.max()), "tip_p95_mm": float(np.percentile(dp, 95)),
            "tip_median_mm": float(np.median(dp)), "view_max_deg": float(dv.max()),
            "view_p95_deg": float(np.percentile(dv, 95))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", help="RUN_DIR[:SEQUENCE] (patient folder of a pipeline run)")
    ap.add_argument("--bounds", default="0.25,0.1,0.05", help="collision_max_error_mm values")
    ap.add_argument("--fractions", default="0.25", help="collision_decimation values")
    ap.add_argument("--repeats", type=int, default=2, help="simulate runs per surface (CPU time: the minimum)")
    ap.add_argument("--name", default="collision_speed")
    ap.add_argument("--from-json", action="store_true", help="only rewrite NAME.md from benchmarks/results/NAME.json")
    args = ap.parse_args()
    res_dir = ROOT / "benchmarks" / "results"
    if args.from_json:
        write_md(json.loads((res_dir / f"{args.name}.json").read_text()), args.name, res_dir)
        return
    bounds = [float(x) for x in args.bounds.split(",")]
    fracs = [float(x) for x in args.fractions.split(",")]
    rows = []
    for spec in args.runs:
        run_dir, _, seq = spec.partition(":")
        run_dir, seq = Path(run_dir), seq or "sequence_000"
        traj, full = inputs(run_dir, seq, "render")       # the render mesh, entrance opened as the stage does
        pp = PatientPaths(run_dir.parent, run_dir.name)
        closed = read_obj(pp.mesh)
        graph = json.loads(pp.centreline_graph.read_text())
        root_r = float(next(b for b in graph["branches"] if b["parent"] == -1)["mean_radius"])

        def opened(m: Mesh) -> Mesh:
            return open_entrance(m, traj.poses[0, :3, 3], traj.poses[0, :3, 2], root_r)[0]
        ref, cpu_ref, wall_ref = sim(traj, full, args.repeats)
        dur = float(ref.report["duration_s"])
        rev, _, _ = sim(traj, Mesh(full.vertices, full.faces[::-1].copy()), 1)
        base = {"run": f"{run_dir.name}/{seq}", "frames": int(len(traj.timestamps)), "duration_s": dur}
        rows.append({**base, "surface": "render mesh (reference)", "faces": int(closed.n_faces), "bound_mm": None,
                     "fraction": 1.0, "error": None, "decimation_cpu_s": 0.0, "sim_cpu_s": cpu_ref,
                     "sim_wall_s": wall_ref, "x_realtime_cpu": dur / cpu_ref,
                     "corridor_faces": ref.report["mesh"].get("corridor_faces"),
                     "diff": diff(rev, ref), "diff_is": "render mesh, triangles reversed (Bullet's noise floor)",
                     "load_average": os.getloadavg()})
        print(json.dumps(rows[-1]), flush=True)
        for frac in fracs:
            for b in bounds:
                c0 = time.process_time()
                col, rep = collision_surface(closed, frac, b)         # as the mesh stage makes collision_model.obj
                cdec = time.process_time() - c0
                err = two_sided_error(closed, col) if col.n_faces != closed.n_faces else None
                res, cpu, wall = sim(traj, opened(col), args.repeats)  # as the simulate stage reads it
                rows.append({**base, "surface": f"decimated f={frac} bound={b} mm", "faces": int(col.n_faces),
                             "bound_mm": b, "fraction": frac, "decimation": rep,
                             "error": None if err is None else {
                                 "render_to_collision_max_mm": err["a_to_b_max_mm"],
                                 "collision_to_render_max_mm": err["b_to_a_max_mm"], "p95_mm": err["p95_mm"]},
                             "decimation_cpu_s": cdec, "sim_cpu_s": cpu, "sim_wall_s": wall,
                             "x_realtime_cpu": dur / cpu, "corridor_faces": res.report["mesh"].get("corridor_faces"),
                             "diff": diff(res, ref), "diff_is": "vs the render mesh run",
                             "penetration_max_mm": res.report["penetration_mm"]["max"],
                             "load_average": os.getloadavg()})
                print(json.dumps({k: v for k, v in rows[-1].items() if k != "decimation"}), flush=True)
    out = {"rows": rows, "config": SimParams().to_dict(), "python": platform.python_version(),
           "machine": platform.machine(), "cpu_count": os.cpu_count(),
           "command": f"benchmarks/collision_speed.py --bounds {args.bounds} --fractions {args.fractions} "
                      f"--repeats {args.repeats} --name {args.name} " + " ".join(args.runs)}
    (res_dir / f"{args.name}.json").write_text(json.dumps(out, indent=2) + "\n")
    write_md(out, args.name, res_dir)


def write_md(out: dict, name: str, res_dir: Path) -> None:
    rows = out["rows"]
    repeats = out["command"].split("--repeats ")[1].split()[0]
    lines = [f"# Collision surface: faces, error, simulate speed, tip difference ({name})", "",
             "Reference: the simulate stage's run (default config, corridor) on the whole render mesh. Each decimated "
             "surface is made by `anatomy/decimate.py` (as the mesh stage makes `collision_model.obj`); 'error' is "
             "the measured one-sided distance both ways to the render mesh (render -> collision / collision -> "
             "render, max) and the p95 of both. Simulate CPU = process_time of the call (user+sys), the minimum of "
             f"{repeats} runs; x real time = simulated s / CPU s. Tip / view difference: every frame, against "
             "the reference run; the reference row's difference is the render mesh with its triangles reversed "
             "(the same surface: Bullet's noise floor). 'bound not met': the routine found no reduction within the "
             "bound and returned the render mesh itself.", "",
             "| run | surface | faces | corridor faces | error max mm (r->c / c->r) | p95 mm | decimation CPU s | "
             "simulate CPU s | x real time (CPU) | tip diff max / p95 mm | view diff max deg | load avg |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        e = r["error"]
        es = "-" if e is None else f"{e['render_to_collision_max_mm']:.3f} / {e['collision_to_render_max_mm']:.3f}"
        ps = "-" if e is None else f"{e['p95_mm']:.4f}"
        surf = r["surface"] + (" (bound not met: the render mesh)" if r["faces"] >= (r.get("decimation") or {}).get("faces_input", 1 << 62) else "")
        lines.append(f"| {r['run']} | {surf} | {r['faces']} | {r['corridor_faces']} | {es} | {ps} | "
                     f"{r['decimation_cpu_s']:.1f} | {r['sim_cpu_s']:.2f} | {r['x_realtime_cpu']:.1f} | "
                     f"{r['diff']['tip_max_mm']:.4f} / {r['diff']['tip_p95_mm']:.4f} | "
                     f"{r['diff']['view_max_deg']:.3f} | {r['load_average'][0]:.1f} |")
    lines += ["", f"Command: `{out['command']}`", ""]
    (res_dir / f"{name}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
