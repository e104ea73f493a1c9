"""Every physics step's contacts of one closed-loop navigation episode (issue #19: how the scope tunnels).

    python benchmarks/navigation_contacts.py --output-dir OUTPUT_DIR --patient ID --target BRANCH [--steps N]
                                             [--out FILE.json] [overrides ...]

Runs :func:`room_pipeline.navigation.closed_loop.run_episode` (config ``navigate.episode`` / ``navigate.planner`` /
``simulate``, as ``room navigate episode``) with :class:`~room_pipeline.robot.pybullet_adapter.ScopeSim`'s contact
query recorded at every physics step: the summed normal force (N), and of the deepest contact point its
penetration (mm), link index, world position (mm) and contact normal (on the wall); the tip link's position (mm)
and speed (mm/s), the bending segment's fastest joint (rad/s) and largest joint error from its target (rad); and
every contact point (``all``: link, penetration mm, normal force N, point on the wall mm, normal).  Prints the
outcome and the last ``--steps`` records (default 30; 0: none) before the episode ended; ``--out`` writes every
record and the per-step control log as JSON.  Used for benchmarks/results/navigation_failures.md (sessions 13, 14).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import pybullet as p

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.config.compose import compose  # noqa: E402
from room_pipeline.navigation import closed_loop  # noqa: E402
from room_pipeline.navigation.cli import load_patient, params_from  # noqa: E402


def recorder(records: list):
    """A ScopeSim subclass whose ``contacts()`` appends one record per call (one per physics step in the loop)."""

    class RecordingSim(closed_loop.ScopeSim):
        _t = 0.0

        def step(self, n=1):
            super().step(n)
            self._t += n * self.params.time_step_s

        def contacts(self):
            f, pen = super().contacts()
            cps = [cp for w in self.walls for cp in p.getContactPoints(self.body, w, physicsClientId=self.cid)]
            if cps:
                c = max(cps, key=lambda x: -x[8])
                tip = p.getLinkState(self.body, self.capsules[-1], computeLinkVelocity=1, physicsClientId=self.cid)
                th, om = self.joint_state()
                records.append({"t_s": round(self._t, 4), "force_n": round(f, 5), "penetration_mm": round(pen * 1e3, 4),
                                "points": len(cps), "link": c[3], "pos_mm": [round(x * 1e3, 2) for x in c[5]],
                                "normal": [round(x, 3) for x in c[7]],
                                "tip_link_mm": [round(x * 1e3, 3) for x in tip[4]],
                                "tip_link_speed_mm_s": round(math.sqrt(sum(v * v for v in tip[6])) * 1e3, 2),
                                "joint_speed_max_rad_s": round(float(abs(om).max()), 2),
                                "joint_error_max_rad": round(float(abs(self.targets - th).max()), 4),
                                "all": [[cp[3], round(-cp[8] * 1e3, 4), round(cp[9], 5),
                                         [round(x * 1e3, 2) for x in cp[6]], [round(x, 3) for x in cp[7]]] for cp in cps]})
            return f, pen

    return RecordingSim


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output-dir", required=True)
    ap.add_argument("--patient", required=True)
    ap.add_argument("--target", type=int, required=True)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--out")
    args, overrides = ap.parse_known_args(argv)
    planner, ep, sim = params_from(compose(overrides))
    patient = load_patient(Path(args.output_dir), args.patient)
    records: list = []
    closed_loop.ScopeSim = recorder(records)            # this process only: the episode's simulator records
    c0 = time.process_time()
    res = closed_loop.run_episode(patient, args.target, ep, planner, sim)
    print(f"{args.patient} target {args.target}: {res['outcome']} at {res['time_s']:.1f} s, peak force "
          f"{res['peak_contact_force_n']:.3f} N, generation {res['generation_reached']}, CPU {time.process_time() - c0:.0f} s")
    for r in records[-args.steps:] if args.steps > 0 else []:
        print(json.dumps(r))
    if args.out:
        Path(args.out).write_text(json.dumps({"result": {k: v for k, v in res.items() if k != "log"},
                                              "log": res["log"], "contacts": records}) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
