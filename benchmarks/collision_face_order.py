#!/usr/bin/env python3
"""How far the simulated tip moves when only the ORDER of the wall's triangles changes (the floor under
``tests/test_collision_corridor.py::test_corridor_matches_whole_mesh_on_phantom``).

    python benchmarks/collision_face_order.py [--perms 4] [--name collision_face_order]

The test's phantom (``tests/test_simulation.py``'s ``phantom`` fixture: generation 3, a path 90 mm down the
trachea into branch 3, its lumen mesh) is simulated with the default config on the whole mesh
(``collision_corridor_mm`` 0), then again with the same triangles in ``--perms`` seeded random orders (same
geometry, same vertices), and with the default corridor (which loads a subset of the faces, ordered along the
route).  Bullet's contact manifold and solver visit the triangles in their order, so a contact-rich run is
sensitive to it; this measures that sensitivity as the tip positions' distance to the whole-mesh run (all
frames: max, frame of the max, 95th percentile).  Writes benchmarks/results/NAME.{json,md}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT))

from room_pipeline.robot.kinematics import DEFAULT_GEOMETRY as G  # noqa: E402
from room_pipeline.robot.sim_params import SimParams  # noqa: E402
from room_pipeline.robot.simulation import simulate  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--perms", type=int, default=4)
    ap.add_argument("--name", default="collision_face_order")
    ap.add_argument("--quick", action="store_true", help="one permutation, no results file: runs?")
    args = ap.parse_args()
    from tests.test_simulation import phantom
    _, tr, mesh = phantom.__wrapped__()
    t0 = time.process_time()
    full = simulate(tr, mesh, SimParams(collision_corridor_mm=0.0), G)

    def dev(res) -> dict:
        d = np.linalg.norm(full.tip_poses[:, :3, 3] - res.tip_poses[:, :3, 3], axis=1) * 1e3
        return {"max_mm": float(d.max()), "frame_of_max": int(np.argmax(d)), "p95_mm": float(np.percentile(d, 95))}

    rows = []
    for s in range(1, 2 if args.quick else args.perms + 1):
        faces = np.asarray(mesh.faces)[np.random.default_rng(s).permutation(mesh.n_faces)]
        r = simulate(tr, dataclasses.replace(mesh, faces=faces), SimParams(collision_corridor_mm=0.0), G)
        rows.append({"run": f"whole mesh, faces permuted (seed {s})", **dev(r)})
        print(rows[-1], flush=True)
    corr = simulate(tr, mesh, SimParams(), G)
    rows.append({"run": f"default corridor ({corr.report['mesh']['corridor_faces']} of {mesh.n_faces} faces)",
                 **dev(corr)})
    print(rows[-1], flush=True)
    if args.quick:
        return
    out = {"frames": int(len(full.tip_poses)), "faces": int(mesh.n_faces), "rows": rows,
           "cpu_s": time.process_time() - t0}
    res = ROOT / "benchmarks" / "results"
    (res / f"{args.name}.json").write_text(json.dumps(out, indent=1))
    md = [f"# Tip position vs the whole-mesh run when only the triangles' order changes",
          "", f"`python benchmarks/collision_face_order.py --perms {args.perms}` (the test phantom, "
          f"{out['frames']} frames, {out['faces']} faces; {out['cpu_s']:.0f} CPU s)", "",
          "| run | max mm | frame | p95 mm |", "|---|---|---|---|"]
    md += [f"| {r['run']} | {r['max_mm']:.4f} | {r['frame_of_max']} | {r['p95_mm']:.4f} |" for r in rows]
    (res / f"{args.name}.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
