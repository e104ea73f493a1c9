"""Camera-pose accuracy of an estimated sequence against the ground truth (pure numpy).

Inputs are camera-to-world poses (4x4, OpenCV camera frame, world metres) of
the same N frames, plus a mask of the frames the method registered; the
estimate may live in any world frame and at any scale (monocular methods).

Pairwise metrics (the protocol of PoseDiffusion / VGGT), over all pairs i < j
    The relative pose of camera j seen from camera i is
    ``T_ij = T_i^-1 T_j``: rotation ``R_ij = R_i^T R_j`` and translation
    ``t_ij = R_i^T (c_j - c_i)`` (c = camera centre).  Both are unchanged by a
    rigid motion of the world, and the *direction* of ``t_ij`` also by a
    change of scale, so no alignment is needed.
    * rotation error: the angle of ``R_ij,gt^T R_ij,est`` in degrees, [0, 180];
    * translation error: the angle between ``t_ij,gt`` and ``t_ij,est``,
      sign ambiguity folded: ``min(a, 180 - a)``, in [0, 90] (as VGGT does);
      a zero-length translation has no direction: the error is 0 when both
      are zero, 90 (the worst folded value) when only one is;
    * a pair with an unregistered frame is a failure: both errors 180.
    * ``RRA@tau`` / ``RTA@tau``: share of pairs with rotation / translation
      error strictly below ``tau`` degrees (fractions in [0, 1]);
    * ``AUC@T``: mean over the integer thresholds t = 1 .. T degrees of the
      share of pairs whose larger error ``max(rot, trans)`` is strictly below
      t (a fraction in [0, 1]).

Trajectory metrics
    * registration rate: registered frames / N;
    * ATE: the registered camera centres are aligned to the ground truth by
      the least-squares similarity (Umeyama 1991: scale, rotation,
      translation); ATE is the RMS of the remaining centre distances in mm.
      With fewer than 2 registered frames it is undefined (NaN), never 0.

Nothing registered gives 0 for every accuracy score (RRA, RTA, AUC, rate).
"""
from __future__ import annotations

import dataclasses

import numpy as np

#: error assigned to a pair involving an unregistered frame, degrees
FAILED_PAIR_DEG = 180.0
_EPS = 1e-12


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angle (degrees, [0, 180]) of (..., 3, 3) rotation matrices; accurate near 0 and 180."""
    R = np.asarray(R, dtype=np.float64)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.linalg.norm(v, axis=-1)                       # 2 sin(theta)
    c = np.trace(R, axis1=-2, axis2=-1) - 1.0            # 2 cos(theta)
    return np.degrees(np.arctan2(s, c))


def _as_poses(poses: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected (N, 4, 4) poses, got shape {p.shape}")
    return p


def registered_mask(poses_est: np.ndarray, registered: np.ndarray | None = None) -> np.ndarray:
    """Frames that are registered: the given mask, and in any case only frames whose pose is finite."""
    p = _as_poses(poses_est, "estimated poses")
    finite = np.all(np.isfinite(p.reshape(len(p), -1)), axis=1)
    if registered is None:
        return finite
    m = np.asarray(registered, dtype=bool).reshape(-1)
    if m.shape != finite.shape:
        raise ValueError(f"registered mask has {m.size} entries for {len(p)} poses")
    return m & finite


def pair_indices(n: int) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i, j), i < j, in row-major order."""
    i, j = np.triu_indices(n, k=1)
    return i.astype(np.int64), j.astype(np.int64)


def relative_errors(poses_gt: np.ndarray, poses_est: np.ndarray, registered: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-pair (i, j, rotation error deg, folded translation-direction error deg) over all i < j."""
    gt, est = _as_poses(poses_gt, "ground-truth poses"), _as_poses(poses_est, "estimated poses")
    if len(gt) != len(est):
        raise ValueError(f"{len(gt)} ground-truth poses but {len(est)} estimated poses")
    reg = registered_mask(est, registered)
    i, j = pair_indices(len(gt))
    rot = np.full(len(i), FAILED_PAIR_DEG)
    trans = np.full(len(i), FAILED_PAIR_DEG)
    ok = reg[i] & reg[j]
    if ok.any():
        a, b = i[ok], j[ok]
        est_safe = np.where(reg[:, None, None], est, np.eye(4))

        def rel(P, a, b):
            Ra, Rb = P[a, :3, :3], P[b, :3, :3]
            R = np.einsum("nki,nkj->nij", Ra, Rb)                         # Ra^T Rb
            t = np.einsum("nki,nk->ni", Ra, P[b, :3, 3] - P[a, :3, 3])     # Ra^T (cb - ca)
            return R, t

        Rg, tg = rel(gt, a, b)
        Re, te = rel(est_safe, a, b)
        rot[ok] = rotation_angle_deg(np.einsum("nki,nkj->nij", Rg, Re))
        ng, ne = np.linalg.norm(tg, axis=1), np.linalg.norm(te, axis=1)
        both = (ng > _EPS) & (ne > _EPS)
        cosang = np.einsum("ni,ni->n", tg, te) / np.where(both, ng * ne, 1.0)
        ang = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
        ang = np.minimum(ang, 180.0 - ang)
        none = (ng <= _EPS) & (ne <= _EPS)
        trans[ok] = np.where(both, ang, np.where(none, 0.0, 90.0))
    return i, j, rot, trans


def accuracy_at(errors_deg: np.ndarray, tau_deg: float) -> float:
    """Share of errors strictly below ``tau_deg`` (0 for no pairs)."""
    e = np.asarray(errors_deg, dtype=np.float64)
    return float(np.mean(e < tau_deg)) if e.size else 0.0


def auc(rot_err_deg: np.ndarray, trans_err_deg: np.ndarray, max_deg: int = 30) -> float:
    """Mean over t = 1 .. max_deg of the share of pairs with ``max(rot, trans) < t`` (fraction in [0, 1])."""
    if max_deg < 1:
        raise ValueError("max_deg must be >= 1")
    e = np.maximum(np.asarray(rot_err_deg, dtype=np.float64), np.asarray(trans_err_deg, dtype=np.float64))
    if e.size == 0:
        return 0.0
    thresholds = np.arange(1, int(max_deg) + 1, dtype=np.float64)
    return float(np.mean([(e < t).mean() for t in thresholds]))


@dataclasses.dataclass(frozen=True)
class Sim3:
    """x_aligned = scale * R @ x + t."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, dtype=np.float64) @ self.R.T + self.t


def umeyama_sim3(src: np.ndarray, dst: np.ndarray) -> Sim3:
    """Least-squares similarity mapping points ``src`` (N, 3) onto ``dst`` (N, 3), N >= 2 (Umeyama 1991)."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 2:
        raise ValueError(f"umeyama_sim3 needs two (N, 3) arrays with N >= 2, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = float(np.mean(np.sum(xs * xs, axis=1)))
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / var_s) if var_s > _EPS else 1.0
    return Sim3(scale, R, mu_d - scale * R @ mu_s)


def ate(poses_gt: np.ndarray, poses_est: np.ndarray, registered: np.ndarray | None = None
        ) -> tuple[float, np.ndarray, Sim3 | None]:
    """ATE RMSE (mm) of the registered centres after Sim(3) alignment, per-frame errors (mm, NaN if unregistered).

    Ground truth in metres.  Fewer than 3 registered frames: (NaN, all NaN, None) -- a similarity
    maps any two points onto any other two exactly, so an ATE of two frames would read as a perfect 0.
    """
    gt, est = _as_poses(poses_gt, "ground-truth poses"), _as_poses(poses_est, "estimated poses")
    reg = registered_mask(est, registered)
    per = np.full(len(gt), np.nan)
    if reg.sum() < 3:
        return float("nan"), per, None
    sim = umeyama_sim3(est[reg, :3, 3], gt[reg, :3, 3])
    d = np.linalg.norm(sim.apply(est[reg, :3, 3]) - gt[reg, :3, 3], axis=1) * 1e3
    per[reg] = d
    return float(np.sqrt(np.mean(d * d))), per, sim


def pose_metrics(poses_gt: np.ndarray, poses_est: np.ndarray, registered: np.ndarray | None = None,
                 tau_deg: float = 5.0, auc_max_deg: int = 30) -> dict:
    """Every score of one sequence as a flat dict (fractions in [0, 1], angles in degrees, ATE in mm)."""
    gt = _as_poses(poses_gt, "ground-truth poses")
    est = _as_poses(poses_est, "estimated poses")
    reg = registered_mask(est, registered)
    _, _, rot, trans = relative_errors(gt, est, reg)
    ate_mm, _, sim = ate(gt, est, reg)
    ok = rot < FAILED_PAIR_DEG
    tau = f"{tau_deg:g}"
    return {
        f"RRA@{tau}": accuracy_at(rot, tau_deg),
        f"RTA@{tau}": accuracy_at(trans, tau_deg),
        f"AUC@{int(auc_max_deg)}": auc(rot, trans, auc_max_deg),
        "registration_rate": float(reg.mean()) if len(reg) else 0.0,
        "n_frames": int(len(gt)),
        "n_registered": int(reg.sum()),
        "n_pairs": int(len(rot)),
        "rotation_error_median_deg": float(np.median(rot[ok])) if ok.any() else float("nan"),
        "translation_error_median_deg": float(np.median(trans[ok])) if ok.any() else float("nan"),
        "ate_rmse_mm": ate_mm,
        "sim3_scale": float(sim.scale) if sim is not None else float("nan"),
    }


def per_frame_errors(poses_gt: np.ndarray, poses_est: np.ndarray, registered: np.ndarray | None = None) -> dict:
    """Per-frame curves for plots (NaN where undefined).

    ``position_error_mm``: centre distance after the Sim(3) alignment;
    ``orientation_error_deg``: angle between the aligned and the true camera orientation;
    ``step_rotation_error_deg`` / ``step_translation_error_deg``: the pair (i-1, i) errors (NaN for frame 0).
    """
    gt = _as_poses(poses_gt, "ground-truth poses")
    est = _as_poses(poses_est, "estimated poses")
    reg = registered_mask(est, registered)
    n = len(gt)
    _, pos, sim = ate(gt, est, reg)
    ori = np.full(n, np.nan)
    if sim is not None:
        Ra = np.einsum("ij,njk->nik", sim.R, est[reg, :3, :3])
        ori[reg] = rotation_angle_deg(np.einsum("nki,nkj->nij", gt[reg, :3, :3], Ra))
    step_r, step_t = np.full(n, np.nan), np.full(n, np.nan)
    for k in range(1, n):
        _, _, r, t = relative_errors(gt[k - 1:k + 1], est[k - 1:k + 1], reg[k - 1:k + 1])
        step_r[k], step_t[k] = r[0], t[0]
    return {"registered": reg, "position_error_mm": pos, "orientation_error_deg": ori,
            "step_rotation_error_deg": step_r, "step_translation_error_deg": step_t}


def segment_scores(poses_gt: np.ndarray, poses_est: np.ndarray, registered: np.ndarray | None,
                   labels: list[str], tau_deg: float = 5.0, auc_max_deg: int = 30) -> dict:
    """RRA / RTA / AUC per route segment: over the pairs i < j whose two frames carry the same label; plus
    ``bifurcations``, pooling the pairs inside any label that starts with ``bifurcation``.  Each entry also
    has ``n_frames``, ``n_pairs`` and the registration rate of its frames."""
    lab = np.asarray(labels, dtype=object)
    if len(lab) != len(_as_poses(poses_gt, "ground-truth poses")):
        raise ValueError(f"{len(lab)} labels for {len(poses_gt)} frames")
    i, j, rot, trans = relative_errors(poses_gt, poses_est, registered)
    reg = registered_mask(poses_est, registered)
    same = lab[i] == lab[j]
    tau = f"{tau_deg:g}"
    groups = {str(n): same & (lab[i] == n) for n in dict.fromkeys(labels)}
    bif = same & np.array([str(x).startswith("bifurcation") for x in lab[i]], dtype=bool)
    if bif.any():
        groups["bifurcations"] = bif
    out = {}
    for name, m in groups.items():
        frames = (lab == name) if name != "bifurcations" else np.array(
            [str(x).startswith("bifurcation") for x in lab], dtype=bool)
        out[name] = {f"RRA@{tau}": accuracy_at(rot[m], tau_deg), f"RTA@{tau}": accuracy_at(trans[m], tau_deg),
                     f"AUC@{int(auc_max_deg)}": auc(rot[m], trans[m], auc_max_deg),
                     "registration_rate": float(reg[frames].mean()) if frames.any() else 0.0,
                     "n_frames": int(frames.sum()), "n_pairs": int(m.sum())}
    return out
