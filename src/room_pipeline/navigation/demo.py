"""The ROOM paper's navigation demonstration on frames of a rendered sequence (``room navigate demo``).

For each chosen frame: depth (the ground truth, or a registered estimator's prediction median-scaled to
the ground truth as the paper does) -> camera-frame point cloud (:mod:`.perception`) -> the farthest free
visible point and a path to it (:mod:`.planner`: constant-curvature arcs within the scope's curvature limit,
checked against the cloud with the scope's collision spheres) -> the path in the camera and world frames,
the frame's RGB with the projected path and goal (PNG), a PLY of the cloud and path (world frame, for any
3-D viewer), and whether the path collides with the TRUE lumen (:class:`.lumen.TrueLumen`: signed distance
of every collision sphere's centre to the rendered mesh), which the paper could not measure.

Outputs (``--out``): ``navigation_demo.json`` (units and frames stated in it), ``frame_NNNN_path.png``,
``frame_NNNN_path.ply``; written through temporary files and renamed, removed again if the run fails.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..catalog import SequencePaths
from ..conventions import metadata_block
from ..errors import InputError
from ..io.atomic import write_bytes
from ..io.mesh import read_obj
from ..paths import PatientPaths
from ..render.camera import CameraIntrinsics
from .lumen import TrueLumen
from .perception import back_project, median_scale
from .planner import Plan, PlannerParams, choose_goal, plan_path


def draw_path(rgb: np.ndarray, camera: CameraIntrinsics, plan: Plan, goal: np.ndarray | None,
              collides: bool) -> np.ndarray:
    """The RGB frame with the projected path (green: clear of the true lumen, red: collides) and goal (cyan)."""
    import cv2

    img = np.ascontiguousarray(rgb[..., :3].copy())
    pts = plan.points[plan.points[:, 2] > camera.near]
    colour = (255, 40, 40) if collides else (40, 255, 60)
    thick = max(1, camera.width // 200)
    if len(pts) >= 2:
        uv = np.round(camera.project(pts)).astype(np.int32)
        cv2.polylines(img, [uv.reshape(-1, 1, 2)], False, colour, thick, cv2.LINE_AA)
    if goal is not None:
        g = np.round(camera.project(goal[None])[0]).astype(int)
        cv2.circle(img, (int(g[0]), int(g[1])), 3 * thick + 2, (0, 230, 255), thick, cv2.LINE_AA)
    return img


def _png_bytes(img: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[..., ::-1]))
    if not ok:
        raise InputError("could not encode the path image as PNG")
    return buf.tobytes()


def _ply_bytes(points: np.ndarray, colours: np.ndarray) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\ncomment world RAS+ metres\nelement vertex {len(points)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode()
    rec = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    rec["r"], rec["g"], rec["b"] = colours[:, 0], colours[:, 1], colours[:, 2]
    return head + rec.tobytes()


def route_command(positions: np.ndarray, i: int, pose: np.ndarray, camera: CameraIntrinsics,
                  ahead_m: float = 0.03, min_offset: float = 0.1) -> np.ndarray | None:
    """The operator's image-plane command (unit (u, v)) toward where the sequence's own route goes.

    The first later camera position at least ``ahead_m`` (m) from frame ``i``'s (else the last), projected into
    frame ``i``; None when it lies behind the camera or within ``min_offset`` x the image width of the centre
    (straight on: no turn to ask for).  The closed loop's operator says left/right/up/down at a bifurcation; here
    the direction is the route's own, so the goal is sought in the opening the sequence enters."""
    P = np.asarray(positions, dtype=np.float64)
    d = np.linalg.norm(P[i:] - P[i], axis=1)
    j = i + int(np.argmax(d >= ahead_m)) if (d >= ahead_m).any() else len(P) - 1
    x = np.linalg.inv(pose) @ np.r_[P[j], 1.0]
    if j == i or x[2] <= camera.near:
        return None
    off = camera.project(x[None, :3])[0] - np.array([camera.cx, camera.cy])
    n = float(np.linalg.norm(off))
    return off / n if n >= min_offset * camera.width else None


def demo_frame(depth: np.ndarray, pose: np.ndarray, camera: CameraIntrinsics, params: PlannerParams,
               lumen: TrueLumen | None, stride: int, command: np.ndarray | None = None) -> dict:
    """Plan on one depth map; the plan, the goal and the true-lumen check (dict; arrays as numpy).
    ``command``: unit (u, v) image direction of the opening to take (None: the deepest opening)."""
    cloud = back_project(depth, camera, stride)
    if len(cloud.points) == 0:
        raise InputError("the depth map has no valid pixel: nothing to plan on")
    goal = choose_goal(cloud, params, command)
    if goal is None:
        return {"cloud": cloud, "goal": None, "plan": None, "true_lumen": None}
    plan = plan_path(cloud, goal.point, params)
    pw, tw = plan.to_world(pose)
    true = lumen.path_report(pw, params.scope_radius_mm * 1e-3) if lumen is not None else None
    return {"cloud": cloud, "goal": goal, "plan": plan, "world_points": pw, "world_tangents": tw, "true_lumen": true}


def run_demo(seq_dir: Path, frames: list[int], out_dir: Path, params: PlannerParams, depth_source: str = "gt",
             stride: int = 2, depth_cfg=None, command: str = "route") -> dict:
    """The demonstration on ``frames`` of the rendered sequence ``seq_dir``; writes into ``out_dir``.
    ``command``: ``route`` (the operator points to the opening the sequence's route enters, :func:`route_command`)
    or ``none`` (the deepest opening, whichever way the route goes)."""
    from ..dataset.reader import SequenceReader

    seq_dir = Path(seq_dir)
    sp = SequencePaths(seq_dir)
    if not sp.render_json.exists():
        raise InputError(f"{seq_dir}: not a rendered sequence (no {sp.render_json.relative_to(seq_dir)})")
    if command not in ("route", "none"):
        raise InputError(f"--command must be route or none, got {command!r}")
    reader = SequenceReader(seq_dir, ["rgb"])
    from ..catalog import RENDER_JSON
    from ..io.records import POSE_KEY, pose_track_from_doc

    positions = pose_track_from_doc(json.loads(sp.render_json.read_text()), POSE_KEY[RENDER_JSON],
                                    sp.render_json).positions
    mesh_path = PatientPaths(seq_dir.parent.parent, seq_dir.parent.name).mesh
    lumen = TrueLumen(read_obj(mesh_path))
    ids = set(reader.frame_ids)
    estimator = None
    if depth_source != "gt":
        from ..depth.estimators import BackendUnavailable, ConfigError, DepthParams, SequenceInfo, create

        cam0 = CameraIntrinsics.from_dict(json.loads(sp.camera.read_text()))
        rend = json.loads(sp.render_json.read_text()).get("renderer")
        info = SequenceInfo(camera=cam0, root=seq_dir, patient=seq_dir.parent.name, sequence=seq_dir.name,
                            renderer=rend, output_dir=seq_dir.parent.parent)
        try:
            estimator = create(depth_source, DepthParams.from_dict(depth_cfg), info)
        except ConfigError as exc:
            raise InputError(f"--depth: {exc} (gt or a method of the depth registry)") from None
        except BackendUnavailable as exc:
            raise InputError(f"--depth {depth_source}: cannot run here: {exc}") from None
    results, files = [], {}
    for i in frames:
        if i not in ids:
            raise InputError(f"{seq_dir}: no frame {i} (frames {min(ids)}..{max(ids)})")
        dfile = seq_dir / "depth" / f"frame_{i:04d}.exr"
        if not dfile.exists():
            raise InputError(f"{seq_dir}: frame {i} has no depth ({dfile} missing)")
        fr = SequenceReader(seq_dir, ["rgb", "depth"]).frame(i)
        K = fr["intrinsics"]
        cam = CameraIntrinsics(int(K["width"]), int(K["height"]), float(K["fx"]), float(K["fy"]), float(K["cx"]),
                               float(K["cy"]))
        gt = fr["depth"].astype(np.float64)
        scale = None
        if estimator is not None:
            from ..depth.estimators import Frame
            from ..depth.metrics import fit_to_shape

            pred = fit_to_shape(estimator.predict(Frame(fr["rgb"], cam, i)), gt.shape,
                                bool(getattr(estimator, "resizes", False)), f"--depth {depth_source}")
            pred = pred.astype(np.float64)
            depth, scale = median_scale(pred, gt)
        else:
            depth = gt
        cmd = route_command(positions, reader.frame_ids.index(i), fr["pose"], cam) if command == "route" else None
        r = demo_frame(depth, fr["pose"], cam, params, lumen, stride, cmd)
        name = f"frame_{i:04d}"
        entry = {"frame": i, "depth_source": depth_source, "median_scale": scale, "points": int(len(r["cloud"].points)),
                 "command": command, "command_uv": None if cmd is None else np.round(cmd, 6).tolist(),
                 "goal_regions": None if r["goal"] is None else r["goal"].regions}
        if r["plan"] is None:
            entry.update({"goal": None, "reason": "no free point farther than the scope radius"})
            results.append(entry)
            continue
        pl, goal = r["plan"], r["goal"]
        # the true lumen check of the goal itself too, and whether the depth used was ground truth
        entry.update({
            "goal_camera_m": goal.point.tolist(), "goal_depth_m": goal.depth,
            "path_camera_m": np.round(pl.points, 7).tolist(), "path_world_m": np.round(r["world_points"], 7).tolist(),
            "tangents_world": np.round(r["world_tangents"], 7).tolist(),
            "length_m": pl.length, "max_curvature_per_m": pl.max_curvature(), "kappa_max_per_m": params.kappa_max,
            "min_clearance_to_cloud_m": float(pl.clearance.min()),
            "end_to_goal_m": float(np.linalg.norm(pl.points[-1] - goal.point)),
            "collision_free_against_cloud": pl.collision_free,
            # the planner's answer: a collision-free path, or none (the best colliding one is kept to inspect)
            "status": "free path" if pl.collision_free else "no free path",
            "true_lumen": r["true_lumen"],
        })
        results.append(entry)
        files[f"{name}_path.png"] = _png_bytes(draw_path(fr["rgb"], cam, pl, goal.point,
                                                         r["true_lumen"]["collides_with_true_lumen"]))
        cw = r["cloud"].points @ fr["pose"][:3, :3].T + fr["pose"][:3, 3]
        pts = np.vstack([cw, r["world_points"]])
        col = np.vstack([np.tile([200, 120, 110], (len(cw), 1)), np.tile([40, 255, 60], (len(r["world_points"]), 1))])
        files[f"{name}_path.ply"] = _ply_bytes(pts, col.astype(np.uint8))
    if estimator is not None:
        estimator.close()
    doc = {"sequence": str(seq_dir), "planner": dataclasses.asdict(params), "stride": stride,
           "frames": results,
           "units": {"lengths": "m", "curvature": "1/m"},
           "frames_convention": "path_camera_m: OpenCV camera frame of the frame's pose (x right, y down, z forward); "
                                "path_world_m: world RAS+; true_lumen: signed distance of each collision sphere's "
                                "centre to anatomy/lung_model.obj (negative inside the lumen)",
           "conventions": metadata_block()}
    write_outputs(out_dir, {"navigation_demo.json": (json.dumps(doc, indent=1) + "\n").encode(), **files})
    return doc


def write_outputs(out_dir: Path, files: dict[str, bytes]) -> None:
    """Every file written to a temporary name and renamed; on failure none of them remains."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    done: list[Path] = []
    try:
        for name, data in files.items():
            write_bytes(out_dir / name, data)
            done.append(out_dir / name)
    except BaseException:
        for p in done:
            p.unlink(missing_ok=True)
        raise
