"""``room navigate``: the paper's navigation demonstration and closed-loop episodes.

    room navigate demo SEQUENCE_DIR --out DIR [--frames 0,100] [--depth gt|METHOD] [--stride N]
                       [--command route|none] [overrides]
        Plan from the depth of chosen frames of a rendered sequence (:mod:`.demo`); METHOD is any name of
        the depth registry (``depth.methods``), median-scaled to the ground truth.
    room navigate episode --output-dir DIR --patient ID --target BRANCH [--policy depth|darkest|oracle]
                          [--out FILE.json] [overrides]
        One closed-loop episode (:mod:`.closed_loop`) on a patient whose anatomy stages have run; the depth
        policy plans on ``navigate.depth`` (gt or an estimator on the rendered RGB, :mod:`.depth_source`) with
        ``navigate.noise`` (sensor-noise beta), e.g. ``navigate.depth=shading_sfs navigate.noise=1``.
    room navigate targets --output-dir DIR --patient ID [--generation 4]
        The eligible target branches of a generation (navigate.benchmark.min_route_radius_mm).

Overrides are Hydra-style ``key=value`` on the composed config (e.g. ``navigate.episode.max_time_s=30``).
Bad requests (an unknown target, a frame without depth, an unknown estimator) end with one ``room: error:`` line, exit 2.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from ..errors import InputError, RoomError


def _cfg(overrides):
    from ..config.compose import compose

    return compose(list(overrides))


def _section(cfg, key: str) -> dict:
    from ..config.compose import section

    return section(cfg, key)


def load_patient(output_dir: Path, patient: str):
    """The patient's meshes and centreline graph (anatomy stages' outputs)."""
    from ..anatomy.centreline import CentrelineGraph
    from ..io.mesh import read_obj
    from ..paths import PatientPaths
    from .airways import Patient

    pp = PatientPaths(Path(output_dir), patient)
    for f in (pp.mesh, pp.collision_mesh, pp.centreline_graph):
        if not f.exists():
            raise InputError(f"{f} missing: run the anatomy stages first (room run --patient {patient} --until medial_axis)")
    return Patient(patient, read_obj(pp.mesh), read_obj(pp.collision_mesh),
                   CentrelineGraph.from_dict(json.loads(pp.centreline_graph.read_text())))


def params_from(cfg):
    """(PlannerParams, EpisodeParams, SimParams) of a composed config."""
    from ..robot.sim_params import SimParams
    from .params import EpisodeParams
    from .planner import PlannerParams

    nav = _section(cfg, "navigate")
    return (PlannerParams.from_dict(nav.get("planner")), EpisodeParams.from_dict(nav.get("episode")),
            SimParams.from_dict(_section(cfg, "simulate")))


def _frames(text: str) -> list[int]:
    try:
        out = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"--frames must be comma-separated frame numbers, got {text!r}") from None
    if not out:
        raise InputError("--frames is empty")
    return out


def cmd_demo(args) -> int:
    from .demo import run_demo

    from .planner import PlannerParams

    cfg = _cfg(args.overrides)
    planner = PlannerParams.from_dict(_section(cfg, "navigate").get("planner"))
    if args.stride < 1:
        raise InputError(f"--stride must be >= 1, got {args.stride}")
    seq = Path(args.sequence)
    out = Path(args.out)
    doc = run_demo(seq, _frames(args.frames), out, planner, args.depth, args.stride, _section(cfg, "depth"),
                   args.command)
    for f in doc["frames"]:
        if f.get("plan") is None and f.get("goal") is None and "reason" in f:
            print(f"frame {f['frame']}: {f['reason']}")
            continue
        t = f["true_lumen"]
        if not f["collision_free_against_cloud"]:
            print(f"frame {f['frame']}: no free path to the goal at {f['goal_depth_m'] * 1e3:.1f} mm depth (best colliding "
                  f"path kept in the JSON to inspect: min sphere clearance to the true lumen "
                  f"{f['true_lumen']['min_sphere_clearance_mm']:.2f} mm)")
            continue
        print(f"frame {f['frame']}: goal at {f['goal_depth_m'] * 1e3:.1f} mm depth, path {f['length_m'] * 1e3:.1f} mm "
              f"ending {f['end_to_goal_m'] * 1e3:.1f} mm from it, max curvature {f['max_curvature_per_m']:.1f} 1/m, "
              f"free vs cloud {f['collision_free_against_cloud']}, collides with the true lumen "
              f"{t['collides_with_true_lumen']} (min sphere clearance {t['min_sphere_clearance_mm']:.2f} mm)")
    print(f"wrote {out}")
    return 0


def cmd_episode(args) -> int:
    import dataclasses

    from ..io.atomic import write_text
    from .airways import check_target

    cfg = _cfg(args.overrides)
    patient = load_patient(Path(args.output_dir), args.patient)
    check_target(patient.graph, args.target)          # before the physics is imported (pybullet prints a banner)
    from .depth_source import NavPerception, loop_camera, make_depth_source

    nav = _section(cfg, "navigate")           # the estimator too is checked before the physics is imported
    perc = NavPerception.from_navigate(nav)
    planner, ep, sim = params_from(cfg)
    if args.policy:
        ep = dataclasses.replace(ep, policy=args.policy)
    src = None
    if ep.policy == "depth":
        src = make_depth_source(perc, _section(cfg, "depth"), _section(cfg, "noise"),
                                loop_camera(ep.image_px, ep.fov_deg), Path(args.output_dir))
    from .closed_loop import run_episode

    res = run_episode(patient, args.target, ep, planner, sim, depth_source=src)
    res["perception"] = {"depth": perc.depth if src is not None else "gt", "noise": perc.noise if src else 0.0}
    summary = {k: v for k, v in res.items() if k != "log"}
    print(json.dumps(summary, indent=1))
    if args.out:
        write_text(args.out, json.dumps(res, indent=1) + "\n")
    return 0


def cmd_targets(args) -> int:
    from .airways import generation_targets

    from .params import BenchmarkParams

    cfg = _cfg(args.overrides)
    bench = BenchmarkParams.from_dict(_section(cfg, "navigate").get("benchmark"))
    patient = load_patient(Path(args.output_dir), args.patient)
    ids = generation_targets(patient.graph, args.generation, bench.min_route_radius_mm)
    print(" ".join(str(i) for i in ids))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="room navigate", description="vision-based navigation of the simulated scope")
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="plan on chosen frames of a rendered sequence (the paper's demonstration)")
    d.add_argument("sequence")
    d.add_argument("--frames", default="0")
    d.add_argument("--depth", default="gt", help="gt or a depth method of the registry (median-scaled to gt)")
    d.add_argument("--stride", type=int, default=6, help="back-project every N-th row and column (600 px / 6: 10k points)")
    d.add_argument("--command", choices=("route", "none"), default="route",
                   help="route: seek the goal in the opening the sequence's route enters (the operator's word); "
                        "none: the deepest opening")
    d.add_argument("--out", required=True, help="output folder (not inside the DVC-tracked sequence folder)")
    d.set_defaults(func=cmd_demo)
    e = sub.add_parser("episode", help="one closed-loop episode")
    e.add_argument("--output-dir", required=True)
    e.add_argument("--patient", required=True)
    e.add_argument("--target", type=int, required=True)
    e.add_argument("--policy", choices=("depth", "darkest", "oracle"))
    e.add_argument("--out")
    e.set_defaults(func=cmd_episode)
    t = sub.add_parser("targets", help="eligible target branches of a generation")
    t.add_argument("--output-dir", required=True)
    t.add_argument("--patient", required=True)
    t.add_argument("--generation", type=int, default=4)
    t.set_defaults(func=cmd_targets)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(list(argv) if argv is not None else None)
    bad = [x for x in extra if x.startswith("-") or "=" not in x]
    if bad:
        parser.error(f"unrecognized arguments: {' '.join(bad)}")
    args.overrides = extra
    try:
        return int(args.func(args) or 0)
    except RoomError as exc:
        print(f"room: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
