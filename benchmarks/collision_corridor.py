"""The scope's wall as the route's corridor vs the whole collision mesh (issue #17 item 4).

    .venv/bin/python benchmarks/collision_corridor.py RUN_DIR[:SEQUENCE] ... [--name collision_corridor]

Each RUN_DIR is a patient folder written by the pipeline up to the trajectory stage, e.g.
``room run patients=shared_masks --patient atm_001 --until trajectory output_dir=/tmp/x`` -> /tmp/x/atm_001
(or the default phantom: ``room run patients=phantom_single --until trajectory output_dir=/tmp/p`` -> /tmp/p/patient_000).
For each, the simulate stage's inputs (collision_model.obj with the entrance opened, trajectory.json) are
simulated with the default config twice: ``collision_corridor_mm`` at its default and 0 (the whole mesh,
cut into <= max_body_faces bodies; one body where it fits PyBullet's one-shape limit).  Reported: faces
loaded, bodies, the tip position / view direction difference between the two runs (all frames), CPU time
(time.process_time of the simulate call: user+sys of this process) and wall time, realtime factors, the
corridor margin, and the load average (wall time is shared with other jobs; CPU time is the figure).
Writes benchmarks/results/NAME.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.io.mesh import Mesh, read_obj  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402
from room_pipeline.robot.kinematics import ScopeGeometry  # noqa: E402
from room_pipeline.robot.sim_params import SimParams  # noqa: E402
from room_pipeline.robot.simulation import simulate  # noqa: E402
from room_pipeline.robot.sequence_sim import open_entrance  # noqa: E402

PYBULLET_ONE_SHAPE_OK = 131_708     # ../shared/DESIGN.md: passed; 200,914 failed
#: --wall: the simulate stage's wall (collision_model.obj) or the finer render mesh (lung_model.obj), a larger
#: surface of the same anatomy, to see the corridor where the whole mesh is large
WALLS = {"collision": "collision_mesh", "render": "mesh"}       # PatientPaths properties


def inputs(run_dir: Path, sequence: str, wall: str = "collision"):
    pp = PatientPaths(run_dir.parent, run_dir.name)
    doc = json.loads(pp.seq(sequence).trajectory.read_text())
    fr = doc["frames"]
    traj = types.SimpleNamespace(timestamps=np.array([f["timestamp"] for f in fr]),
                                 poses=np.array([f["pose"] for f in fr]),
                                 arclength=np.array([f["arclength"] for f in fr]),
                                 # a joint-space plan (the default trajectory.joint_plan): the shaft's path and the
                                 # joints, as the simulate stage reads them (without them: pose IK on the camera poses)
                                 path_poses=np.array([f["path_pose"] for f in fr]) if "path_pose" in fr[0] else None,
                                 joints=np.array([f["q"] for f in fr]) if "q" in fr[0] else None)
    graph = json.loads(pp.centreline_graph.read_text())
    root_r = float(next(b for b in graph["branches"] if b["parent"] == -1)["mean_radius"])
    mesh, _ = open_entrance(read_obj(getattr(pp, WALLS[wall])), traj.poses[0, :3, 3],
                            traj.poses[0, :3, 2], root_r)
    return traj, mesh


def corridor_plus_rest(traj, mesh, params):
    """The whole mesh loaded as the corridor run's own bodies (the same triangles, order and cut) plus every
    left-out triangle in further bodies: against the corridor run, the only difference is the wall the corridor
    leaves out, so Bullet's sensitivity to the triangle order (a different BVH, contact order) is out of the
    comparison; a difference means the scope reached a left-out triangle."""
    from room_pipeline.robot import pybullet_adapter as ps

    orig = ps.ScopeSim.set_wall
    n = np.int64(len(mesh.vertices))

    def key(F):                    # one integer per triangle (its sorted vertex indices)
        F = np.sort(np.asarray(F, np.int64), axis=1)
        return (F[:, 0] * n + F[:, 1]) * n + F[:, 2]

    def set_wall(self, vertices, faces, order=None):
        orig(self, vertices, faces, order)
        rest = mesh.faces[~np.isin(key(mesh.faces), key(faces))]
        self.add_wall(vertices, rest)

    ps.ScopeSim.set_wall = set_wall
    try:
        return timed(traj, mesh, params)
    finally:
        ps.ScopeSim.set_wall = orig


def timed(traj, mesh, params):
    c0, w0 = time.process_time(), time.perf_counter()
    res = simulate(traj, mesh, params, ScopeGeometry())
    return res, time.process_time() - c0, time.perf_counter() - w0


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", help="RUN_DIR[:SEQUENCE] (patient folder of a pipeline run)")
    ap.add_argument("--name", default="collision_corridor")
    ap.add_argument("--wall", choices=sorted(WALLS), default="collision")
    args = ap.parse_args()
    rows = []
    for spec in args.runs:
        run_dir, _, seq = spec.partition(":")
        run_dir, seq = Path(run_dir), seq or "sequence_000"
        traj, mesh = inputs(run_dir, seq, args.wall)
        corr_p = SimParams()
        res_c, cpu_c, wall_c = timed(traj, mesh, corr_p)
        res_f, cpu_f, wall_f = timed(traj, mesh, SimParams(collision_corridor_mm=0.0))
        # Bullet's own sensitivity to the triangle order: the whole mesh with its faces reversed (same geometry)
        res_r = simulate(traj, Mesh(mesh.vertices, mesh.faces[::-1].copy()), SimParams(collision_corridor_mm=0.0),
                         ScopeGeometry())
        res_p, _, _ = corridor_plus_rest(traj, mesh, corr_p)
        dplus = np.linalg.norm(res_c.tip_poses[:, :3, 3] - res_p.tip_poses[:, :3, 3], axis=1) * 1e3
        dpos = np.linalg.norm(res_c.tip_poses[:, :3, 3] - res_f.tip_poses[:, :3, 3], axis=1) * 1e3
        drev = np.linalg.norm(res_r.tip_poses[:, :3, 3] - res_f.tip_poses[:, :3, 3], axis=1) * 1e3
        dview = angle_deg(res_c.tip_poses[:, :3, 2], res_f.tip_poses[:, :3, 2])
        dur = float(res_c.report["duration_s"])
        mc, mf = res_c.report["mesh"], res_f.report["mesh"]
        row = {"run": f"{run_dir.name}/{seq}", "wall": getattr(PatientPaths(run_dir.parent, run_dir.name), WALLS[args.wall]).stem, "frames": int(len(traj.timestamps)), "duration_s": dur,
               "mesh_faces": int(mesh.n_faces), "fits_one_pybullet_shape": bool(mesh.n_faces <= PYBULLET_ONE_SHAPE_OK),
               "corridor_mm": corr_p.collision_corridor_mm, "corridor_faces": mc.get("corridor_faces"),
               "corridor_bodies": mc["bodies"], "corridor_margin_mm": mc.get("corridor_margin_mm"),
               "corridor_widened": res_c.report["corridor_widened"], "full_bodies": mf["bodies"],
               "tip_diff_mm": {"max": float(dpos.max()), "p95": float(np.percentile(dpos, 95)),
                               "median": float(np.median(dpos))},
               "tip_diff_mm_vs_corridor_plus_rest": {"max": float(dplus.max()), "p95": float(np.percentile(dplus, 95)),
                                                     "rest_bodies": res_p.report["mesh"]["bodies"] - mc["bodies"]},
               "tip_diff_mm_whole_mesh_faces_reversed": {"max": float(drev.max()),
                                                         "p95": float(np.percentile(drev, 95))},
               "view_diff_deg": {"max": float(dview.max()), "p95": float(np.percentile(dview, 95))},
               "cpu_s": {"corridor": cpu_c, "full": cpu_f}, "wall_s": {"corridor": wall_c, "full": wall_f},
               "realtime_factor_cpu": {"corridor": dur / cpu_c, "full": dur / cpu_f},
               "speedup_cpu": cpu_f / cpu_c,
               "tracking_error_mm_corridor": res_c.report["tracking_error_mm"],
               "penetration_max_mm_corridor": res_c.report["penetration_mm"]["max"],
               "load_average": os.getloadavg()}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"rows": rows, "config": SimParams().to_dict(), "python": platform.python_version(),
           "machine": platform.machine(), "cpu_count": os.cpu_count(),
           "command": f"benchmarks/collision_corridor.py --wall {args.wall} --name {args.name} " + " ".join(args.runs)}
    res_dir = ROOT / "benchmarks" / "results"
    (res_dir / f"{args.name}.json").write_text(json.dumps(out, indent=2) + "\n")
    lines = [f"# Collision corridor vs whole mesh ({args.name})", "",
             "Default simulate config; `collision_corridor_mm` default vs 0 (whole mesh, cut into <= "
             f"{SimParams().max_body_faces} faces a body).  CPU = process_time of the simulate call "
             "(user+sys); wall time is shared with other jobs (load average shown).  'faces reversed': the whole "
             "mesh with the same triangles in reverse order against the whole mesh, i.e. Bullet's own sensitivity to "
             "the triangle order (a floor for any change of the wall's triangle set).  'corridor + rest': the whole "
             "mesh loaded as the corridor run's own bodies plus the left-out triangles in further bodies, against the "
             "corridor run: the deterministic comparison (same triangles, order and bodies near the route; a "
             "difference means the scope reached a left-out triangle).", "",
             "| run | frames | sim s | mesh faces | fits one shape | corridor faces / bodies | margin mm | "
             "tip diff vs corridor + rest max / p95 mm | tip diff vs whole mesh max / p95 mm | same, whole mesh with faces reversed | view diff max deg | CPU s corridor / full | x real time (CPU) corridor / full | "
             "speed-up (CPU) | wall s corridor / full | load avg |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['run']} ({r['wall']}) | {r['frames']} | {r['duration_s']:.1f} | {r['mesh_faces']} | "
            f"{'yes' if r['fits_one_pybullet_shape'] else 'no'} | {r['corridor_faces']} / {r['corridor_bodies']} | "
            f"{r['corridor_margin_mm']:.1f} | {r['tip_diff_mm_vs_corridor_plus_rest']['max']:.4f} / "
            f"{r['tip_diff_mm_vs_corridor_plus_rest']['p95']:.4f} | "
            f"{r['tip_diff_mm']['max']:.4f} / {r['tip_diff_mm']['p95']:.4f} | "
            f"{r['tip_diff_mm_whole_mesh_faces_reversed']['max']:.4f} / "
            f"{r['tip_diff_mm_whole_mesh_faces_reversed']['p95']:.4f} | {r['view_diff_deg']['max']:.4f} | {r['cpu_s']['corridor']:.2f} / {r['cpu_s']['full']:.2f} | "
            f"{r['realtime_factor_cpu']['corridor']:.1f} / {r['realtime_factor_cpu']['full']:.1f} | "
            f"{r['speedup_cpu']:.2f} | {r['wall_s']['corridor']:.1f} / {r['wall_s']['full']:.1f} | "
            f"{r['load_average'][0]:.1f} |")
    lines += ["", f"Command: `{out['command']}`", ""]
    (res_dir / f"{args.name}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
