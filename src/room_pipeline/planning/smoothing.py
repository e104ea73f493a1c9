"""Path smoothing under clearance and curvature constraints (step 3 of
:func:`~room_pipeline.planning.trajectory.plan_path`): the convex problem and its ADMM solver, in millimetres
inside."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import sparse
from scipy.ndimage import maximum_filter1d

from ..conventions import MM
from .sdf_fn import SdfFn
from .trajectory_params import TrajectoryParams


@dataclasses.dataclass
class SmoothResult:
    """Output of :func:`smooth_route` (millimetres inside, metres here).

    Attributes:
        points: (N, 3) smoothed path, metres.
        route_s: (N,) route arclength each point projects to, metres.
        margin: (N,) required clearance, metres.
        clearance: (N,) ``-sdf_fn`` at the points, metres.
        max_curvature: discrete (Menger) curvature max, 1/m.
        ok_clearance, ok_curvature: whether each holds.
        fail_index: first failing point, -1 if none.
        iterations: ADMM iterations in all.
    """

    points: np.ndarray
    route_s: np.ndarray
    margin: np.ndarray
    clearance: np.ndarray
    max_curvature: float
    ok_clearance: bool
    ok_curvature: bool
    fail_index: int
    iterations: int


def menger_curvature(points: np.ndarray) -> np.ndarray:
    """Curvature of the circle through each point and its neighbours (N,), ends 0, in 1/units."""
    p = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(p))
    if len(p) < 3:
        return out
    a = p[1:-1] - p[:-2]
    b = p[2:] - p[1:-1]
    c = p[2:] - p[:-2]
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) * np.linalg.norm(c, axis=1)
    out[1:-1] = np.where(den > 0, 2.0 * cross / np.maximum(den, 1e-300), 0.0)
    return out


def _second_diff(N: int) -> sparse.csr_matrix:
    e = np.ones(N)
    return sparse.diags([e[:-2], -2 * e[:-2], e[:-2]], [0, 1, 2], shape=(N - 2, N)).tocsr()


def _banded_upper(A: sparse.spmatrix, u: int) -> np.ndarray:
    """Upper banded storage of a symmetric sparse matrix (for scipy.linalg.cholesky_banded)."""
    n = A.shape[0]
    ab = np.zeros((u + 1, n))
    A = A.tocsr()
    for d in range(u + 1):
        ab[u - d, d:] = A.diagonal(d)
    return ab


class _Admm:
    """ADMM for  min (1/h^3)|D2 P|^2 + lam h |P - C|^2  s.t.  |P_i - C_i| <= rho_i,  |D2 P_i| / h^2 <= k.

    Millimetres.  Both constraint sets are convex (balls around the reference
    centreline points; second-order cones on the discrete curvature vectors),
    and the objective is a convex quadratic, so the problem is convex and ADMM
    (scaled form, residual balancing) converges to its optimum when it is
    feasible.  The x-update is one banded Cholesky solve shared by x, y, z.
    """

    def __init__(self, C: np.ndarray, fixed: np.ndarray, h: float, lam: float):
        self.C, self.h, self.lam = C, h, lam
        N = len(C)
        self.N = N
        self.free = np.flatnonzero(~fixed)
        self.fixed = np.flatnonzero(fixed)
        D2 = _second_diff(N)
        self.D2f = D2[:, self.free].tocsr()
        self.D2fT = self.D2f.T.tocsr()
        self.c_fix = D2[:, self.fixed] @ C[self.fixed]  # fixed points' part of D2 P
        self.Pfix = C[self.fixed]
        self.Q = (self.D2fT @ self.D2f).tocsc()
        self.rho1 = 1.0 / h ** 3
        self.rho2 = 1.0 * h
        self._factor()

    def _factor(self) -> None:
        from scipy.linalg import cholesky_banded
        h = self.h
        F = len(self.free)
        A = self.Q * (2.0 / h ** 3 + self.rho2 / h ** 4) + sparse.identity(F) * (2.0 * self.lam * h + self.rho1)
        self.chol = cholesky_banded(_banded_upper(A, 2))

    def solve(self, radius: np.ndarray, kappa: float, P0: np.ndarray | None = None, max_iter: int = 3000,
              tol: float = 1e-5) -> tuple[np.ndarray, bool, int]:
        """Return (P (N,3) with P_free projected into the balls, converged, iterations)."""
        from scipy.linalg import cho_solve_banded
        h, lam = self.h, self.lam
        Cf = self.C[self.free]
        rad = radius[self.free]
        P = (self.C if P0 is None else P0).copy()
        Z1 = P[self.free].copy()
        U1 = np.zeros_like(Z1)
        W = (self.D2f @ Z1 + self.c_fix) / h ** 2
        Z2 = W.copy()
        U2 = np.zeros_like(Z2)
        rhs0 = -(2.0 / h ** 3) * (self.D2fT @ self.c_fix) + 2.0 * lam * h * Cf
        converged = False
        it = 0
        history: list[float] = []
        for it in range(1, max_iter + 1):
            b = rhs0 + self.rho1 * (Z1 - U1) + (self.rho2 / h ** 2) * (self.D2fT @ (Z2 - U2 - self.c_fix / h ** 2))
            X = cho_solve_banded((self.chol, False), b)
            # balls around the reference points
            v = X + U1 - Cf
            nv = np.linalg.norm(v, axis=1)
            Z1_old = Z1
            Z1 = Cf + v * np.minimum(1.0, rad / np.maximum(nv, 1e-300))[:, None]
            # curvature cones
            W = (self.D2f @ X + self.c_fix) / h ** 2
            w = W + U2
            nw = np.linalg.norm(w, axis=1)
            Z2_old = Z2
            Z2 = w * np.minimum(1.0, kappa / np.maximum(nw, 1e-300))[:, None]
            R1 = X - Z1
            R2 = W - Z2
            U1 += R1
            U2 += R2
            if it % 10 == 0 or it == max_iter:
                r_p = max(float(np.abs(R1).max()), float(np.abs(R2).max()) * h ** 2)
                s_d = max(float(np.abs(Z1 - Z1_old).max()), float(np.abs(Z2 - Z2_old).max()) * h ** 2)
                if r_p < tol and s_d < tol:
                    converged = True
                    break
                if it % 250 == 0:  # stalled primal residual: the constraints cannot all hold
                    history.append(r_p)
                    if len(history) >= 4 and r_p > 100 * tol and r_p > 0.5 * history[-4]:
                        break
                if it % 50 == 0:  # residual balancing
                    if r_p > 10 * s_d and self.rho1 < 1e6 / h ** 3:
                        self.rho1 *= 2.0; self.rho2 *= 2.0; U1 /= 2.0; U2 /= 2.0; self._factor()
                    elif s_d > 10 * r_p and self.rho1 > 1e-3 / h ** 3:
                        self.rho1 /= 2.0; self.rho2 /= 2.0; U1 *= 2.0; U2 *= 2.0; self._factor()
        P = P.copy()
        P[self.fixed] = self.Pfix
        P[self.free] = Z1  # inside the balls: the clearance holds whatever the convergence
        return P, converged, it


def smooth_route(route_points: np.ndarray, route_radius: np.ndarray, route_s: np.ndarray,
                 sdf_fn: SdfFn, kappa_max: float, params: TrajectoryParams) -> SmoothResult:
    """Smooth a route polyline (metres) under the curvature bound and the clearance margin.

    See the module docstring, step 3.  Returns the smoothed points and which
    constraint, if any, fails (checked with the discrete curvature and ``sdf_fn``).
    """
    mm = 1.0 / MM
    V = np.asarray(route_points, dtype=np.float64) * mm
    Rv = np.asarray(route_radius, dtype=np.float64) * mm
    Sv = np.asarray(route_s, dtype=np.float64) * mm
    L = Sv[-1]
    h0 = params.smoothing_step_mm
    N = max(2, int(math.ceil(L / h0)) + 1)
    s_ref = np.linspace(0.0, L, N)
    C = np.stack([np.interp(s_ref, Sv, V[:, k]) for k in range(3)], axis=1)
    if N >= 3:
        # the fixed start direction: the chord over the route's first stretch (2 lumen radii, >= 5 mm), not the
        # centreline's first 0.5 mm, which bends toward the rim where a scan cuts the trachea (CASE091: 124 1/m)
        reach = min(L, max(5.0, 2.0 * float(Rv[0])))
        d = np.array([np.interp(reach, Sv, V[:, k]) for k in range(3)]) - C[0]
        if np.linalg.norm(d) > 1e-9:
            C[1] = C[0] + (s_ref[1] - s_ref[0]) * d / np.linalg.norm(d)
    # lumen clearance of the reference centreline points, from the SDF: ball radii and margin clipping
    clear_c = -sdf_fn(C * MM) * mm
    r_c = np.interp(s_ref, Sv, Rv)
    margin = np.minimum(np.maximum(params.clearance_fraction * r_c, params.clearance_min_mm),
                        params.clearance_max_fraction * np.minimum(r_c, np.maximum(clear_c, 0.0)))
    margin = np.maximum(margin, 0.0)
    buffer = min(0.01, 0.1 * params.clearance_min_mm + 1e-3)  # mm
    radius = np.maximum(np.minimum(r_c, clear_c) - margin - buffer, 0.0)
    fixed = np.zeros(N, dtype=bool)
    fixed[[0, min(1, N - 1), N - 1]] = True
    kmax_mm = kappa_max * MM
    iters = 0
    P = C.copy()
    clear = clear_c
    if N >= 5:
        h = L / (N - 1)
        admm = _Admm(C, fixed, h, params.centring_weight)
        k_aim = params.curvature_safety * kmax_mm
        for relax in range(params.relax_iterations + 1):
            for _ in range(4):  # tighten the aim if the discrete curvature (true spacing) exceeds the bound
                P_try, conv, it = admm.solve(radius, k_aim, P0=P, max_iter=params.max_iterations)
                iters += it
                if not conv:
                    break
                P = P_try
                k_now = float(menger_curvature(P).max())
                if k_now <= params.curvature_safety * kmax_mm * 1.001:
                    break
                k_aim *= params.curvature_safety * kmax_mm / k_now
            if not conv:
                # no path keeps both: the least-bending path in the clearance balls shows where the
                # bend is too sharp (clearance wins, the curvature check below fails)
                P, _, it = admm.solve(radius, np.inf, P0=P, max_iter=params.max_iterations)
                iters += it
            clear = -sdf_fn(P * MM) * mm
            deficit = np.where(fixed, 0.0, margin - clear)
            if relax == params.relax_iterations or not (deficit > 0).any():
                break
            pull = maximum_filter1d(np.where(deficit > 0, deficit + buffer, 0.0), size=max(3, int(2.0 / h) | 1))
            radius = np.maximum(radius - pull, 0.0)  # pull back toward the centreline there
    kap = menger_curvature(P)
    bad_c = (clear < margin) | (clear <= 0)
    bad_c[fixed] = clear[fixed] <= 0  # fixed ends sit on the centreline: only fail if outside the lumen
    bad_k = kap > kmax_mm
    bad = np.flatnonzero(bad_c | bad_k)
    return SmoothResult(P * MM, s_ref * MM, margin * MM, clear * MM, float(kap.max()) * mm,
                        not bad_c.any(), not bad_k.any(), int(bad[0]) if len(bad) else -1, iters)
