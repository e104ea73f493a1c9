"""Multi-view pose evaluation of one rendered sequence (paper Table I): the parameters, the frames, the methods.

:class:`PoseEvalParams` is ``evaluate.pose``; :func:`load_sequence` reads the selected frames, intrinsics and
ground-truth poses; :func:`evaluate_methods` runs every configured method and the trivial baselines and scores
them (:mod:`room_pipeline.evaluate.pose_metrics`, per route segment with :mod:`route_segments`);
:func:`pose_document` and :func:`errors_csv` are the stage's ``pose.json`` and ``pose_errors.csv``.
"""
from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..catalog import RGB_NOISY, SequencePaths
from ..config.params import params_from_dict
from ..errors import ConfigError, InputError
from ..io.images import read_png
from ..io.jsondoc import finite, read_json, round_floats
from ..render.camera import CameraIntrinsics
from . import pose_methods as pm
from .pose_metrics import per_frame_errors, pose_metrics, segment_scores


#: per-frame curves written to pose_errors.csv (column suffixes)
CURVES = ("position_error_mm", "orientation_error_deg", "step_rotation_error_deg", "step_translation_error_deg")


@dataclasses.dataclass(frozen=True)
class PoseEvalParams:
    """Keys of ``evaluate.pose`` in ``conf/evaluate/default.yaml`` (see its comments for units)."""

    methods: tuple = ("sift_vo", "orb_vo")
    images: str = "noisy"
    frame_stride: int = 3
    max_frames: int | None = None
    downscale: float = 2.0
    seed: int = 0
    rra_threshold_deg: float = 5.0
    auc_max_deg: int = 30
    bifurcation_radius_factor: float = 2.0
    colmap: Mapping[str, Any] | None = None
    orb: Mapping[str, Any] | None = None
    sift: Mapping[str, Any] | None = None

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "PoseEvalParams":
        p = params_from_dict(cls, d, "evaluate.pose")
        if p.images not in ("noisy", "clean"):
            raise ConfigError(f"evaluate.pose.images must be 'noisy' or 'clean', got {p.images!r}")
        if p.frame_stride < 1 or p.downscale < 1.0 or p.auc_max_deg < 1 or p.rra_threshold_deg <= 0:
            raise ConfigError("evaluate.pose: frame_stride >= 1, downscale >= 1, auc_max_deg >= 1 and "
                              "rra_threshold_deg > 0 required")
        if p.max_frames is not None and (isinstance(p.max_frames, bool) or not isinstance(p.max_frames, int)
                                         or p.max_frames < 2):
            raise ConfigError(f"evaluate.pose.max_frames must be null or an integer >= 2, got {p.max_frames!r}")
        if not p.methods:
            raise ConfigError("evaluate.pose.methods is empty")
        if p.bifurcation_radius_factor <= 0:
            raise ConfigError("evaluate.pose.bifurcation_radius_factor must be > 0")
        for name in p.methods:
            pm.get_method(str(name))
        return p

    def method_params(self) -> pm.PoseMethodParams:
        return pm.PoseMethodParams(seed=self.seed, colmap=pm.ColmapParams.from_dict(self.colmap),
                                   orb=pm.OrbParams.from_dict(self.orb), sift=pm.SiftParams.from_dict(self.sift))

    def run_names(self) -> list[str]:
        """The configured methods, then the trivial baselines (always scored, once)."""
        names = [str(m) for m in self.methods]
        return names + [b for b in pm.BASELINES if b not in names]


def image_dir(seq: Path, which: str) -> Path:
    """``rgb_noisy/`` when asked for and present, else ``rgb/``."""
    sp = SequencePaths(seq)
    if which == "noisy" and sp.rgb_noisy.is_dir() and any(sp.rgb_noisy.glob("frame_*.png")):
        return sp.folder(RGB_NOISY)
    return sp.folder("rgb")


def load_sequence(seq: Path, p: PoseEvalParams) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, dict]:
    """(images RGB uint8, K (downscaled), ground-truth c2w poses, provenance) of the selected frames."""
    render_json, calib_json = SequencePaths(seq).render_json, SequencePaths(seq).camera
    for f in (render_json, calib_json):
        if not f.is_file():
            raise InputError(f"{f} not found (run the render stage first)")
    frames = read_json(render_json).get("frames") or []
    cam = CameraIntrinsics.from_dict(read_json(calib_json))
    src = image_dir(seq, p.images)
    sel = np.arange(0, len(frames), p.frame_stride)
    if p.max_frames is not None:
        sel = sel[: p.max_frames]
    if len(sel) < 2:
        raise InputError(f"{render_json}: {len(frames)} frames, stride {p.frame_stride}: pose evaluation needs >= 2")
    images, poses = [], []
    for k in sel:
        f = frames[int(k)]
        path = src / f"frame_{int(f['index']):04d}.png"
        im = read_png(path)
        if im.dtype != np.uint8:
            raise InputError(f"{path}: expected an 8-bit image, got {im.dtype}")
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        images.append(np.ascontiguousarray(im[..., :3]))
        poses.append(np.asarray(f["pose"], dtype=np.float64))
    h, w = images[0].shape[:2]
    if (w, h) != (cam.width, cam.height):
        raise InputError(f"{src}: images are {w}x{h} but {calib_json} says {cam.width}x{cam.height}")
    images, K = pm.downscale(images, cam.K, p.downscale)
    info = {"image_dir": src.name, "frame_stride": p.frame_stride, "frames": [int(k) for k in sel],
            "n_frames": len(sel), "rendered_frames": len(frames),
            "image_size": [int(images[0].shape[1]), int(images[0].shape[0])], "downscale": p.downscale,
            "K": np.round(K, 9).tolist()}
    return images, K, np.stack(poses), info


def evaluate_methods(images: list[np.ndarray], K: np.ndarray, poses_gt: np.ndarray, p: PoseEvalParams,
                     labels: list[str] | None = None) -> tuple[dict, dict]:
    """Run every configured method and the trivial baselines: ({name: result record}, {name: per-frame
    curves}) -- unavailable ones too.  With per-frame route ``labels``, each record also has ``segments``."""
    mp = p.method_params()
    results, curves = {}, {}
    for name in p.run_names():
        method = pm.get_method(str(name))
        ok, reason = method.availability(mp)
        if not ok:
            results[name] = {"available": False, "run": True, "reason": reason}
            continue
        res = method.estimate(images, K, mp)
        m = pose_metrics(poses_gt, res.poses_c2w, res.registered, p.rra_threshold_deg, p.auc_max_deg)
        cpu = res.info.get("cpu_seconds")
        results[name] = {"available": True, "run": True, "reason": None, "baseline": bool(getattr(method, "baseline", False)),
                         **m, "seconds": res.seconds, "seconds_per_frame": res.seconds / len(images),
                         "cpu_seconds_per_frame": (cpu / len(images)) if cpu is not None else None,
                         "info": res.info}
        if labels is not None:
            results[name]["segments"] = segment_scores(poses_gt, res.poses_c2w, res.registered, labels,
                                                       p.rra_threshold_deg, p.auc_max_deg)
        curves[name] = per_frame_errors(poses_gt, res.poses_c2w, res.registered)
    for name in pm.METHODS:             # a registered method left out is a row saying so, not a missing row
        if name not in results:
            results[name] = {"available": False, "run": False, "reason": not_run_reason(name, p)}
    return results, curves


def not_run_reason(name: str, p: PoseEvalParams) -> str:
    """Why a registered method has no numbers: it is not in ``evaluate.pose.methods``, and how to run it."""
    methods = ",".join([name] + [str(m) for m in p.methods])
    return (f"not in evaluate.pose.methods; run it with -S 'evaluate.pose.methods=[{methods}]' (dvc exp run) "
            f"or 'evaluate.pose.methods=[{methods}]' (room run)")


def errors_csv(frames: list[int], curves: Mapping[str, dict]) -> str:
    """Per-frame CSV: frame, source frame, then ``<method>_registered`` and ``<method>_<curve>``; empty = undefined."""
    cols = ["frame", "source_frame"]
    for name in curves:
        cols += [f"{name}_registered"] + [f"{name}_{c}" for c in CURVES]
    out = io.StringIO()
    out.write(",".join(cols) + "\n")
    for k, src in enumerate(frames):
        row = [str(k), str(src)]
        for c in curves.values():
            row.append("1" if c["registered"][k] else "0")
            for name in CURVES:
                v = float(c[name][k])
                row.append(f"{v:.6f}" if math.isfinite(v) else "")
        out.write(",".join(row) + "\n")
    return out.getvalue()


UNITS = {"RRA@tau / RTA@tau / AUC@T / registration_rate": "fractions in [0, 1] (the tables print %)",
         "rotation / translation errors": "degrees; translation = angle between relative translation directions, "
                                          "sign folded min(a, 180 - a)",
         "ate_rmse_mm": "mm, RMS camera-centre error after Sim(3) (Umeyama) alignment of the registered frames",
         "seconds": "wall time of the method on this machine (s)", "seconds_per_frame": "s per input frame",
         "cpu_seconds_per_frame": "process CPU time (user + sys) per input frame, s (fair on a shared machine)",
         "baseline": "true for the image-blind trivial baselines (identity, constant_forward)"}


SEGMENTS_DEFINITION = ("bifurcation_<k>: camera centre within bifurcation_radius_factor x the parent lumen radius of "
                       "a branch point; trachea: else nearest centreline point on the root branch; distal: else; "
                       "scores over pairs with both frames in the segment")


def pose_document(results: dict, info: dict, labels: list, regions: Any, p: PoseEvalParams, metadata: dict) -> dict:
    """``pose.json``: per-method results, the input frames, units, route segments and the protocol (finite,
    floats rounded to 6 digits)."""
    n = info["n_frames"]
    tau, T = f"{p.rra_threshold_deg:g}", int(p.auc_max_deg)
    return finite(round_floats({
        "methods": results, "input": info, "units": UNITS,
        "segments": {"labels": labels, "bifurcation_regions": regions, "definition": SEGMENTS_DEFINITION,
                     "bifurcation_radius_factor": p.bifurcation_radius_factor},
        "protocol": f"whole sequence ({n} frames): all {n * (n - 1) // 2} frame pairs i<j; RRA@{tau}/RTA@{tau}: "
                    f"share of pairs under {tau} deg; AUC@{T}: mean over 1..{T} deg thresholds of the share of pairs "
                    f"with max(rot, trans) error under the threshold; pairs with an unregistered frame count 180 deg",
        "metadata": metadata}, 6))


def pose_summary(results: Mapping[str, dict], p: PoseEvalParams) -> dict:
    """{method: {RRA, RTA, AUC, registration rate, ATE, s/frame}} of the available methods (the DVC metrics)."""
    tau, T = f"{p.rra_threshold_deg:g}", int(p.auc_max_deg)
    keys = (f"RRA@{tau}", f"RTA@{tau}", f"AUC@{T}", "registration_rate", "ate_rmse_mm", "seconds_per_frame")
    return {name: {k: round(float(r[k]), 6) for k in keys} for name, r in results.items() if r["available"]}
