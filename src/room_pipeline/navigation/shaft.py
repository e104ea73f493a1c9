"""The closed loop's shaft (issue #19): where the bending segment's base is at insertion ``q3``.

``Trace``: follow-the-leader along the path the tip itself has traced; ``LumenShaft``: the passive insertion
tube conforming to the lumen (the airway's centreline to the tip's branch).  Both expose ``route``
(:class:`~room_pipeline.robot.route.Route`: ``frame(s)`` is the base's world pose at arclength ``s``, m),
``extend(p, z)`` (the tip's position, m, and view direction) and ``s_end`` (the tip's arclength, m).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..robot.route import Route
from .airways import Airways


class Trace:
    """Follow-the-leader path of the shaft: points every >= 1 mm with a rotation-minimising frame."""

    def __init__(self, pose: np.ndarray, back_m: float = 0.2, step: float = 1e-3) -> None:
        z = pose[:3, 2]
        x = pose[:3, 0]
        n = int(round(back_m / step))
        self.P = [pose[:3, 3] - (n - k) * step * z for k in range(n + 1)]
        self.X = [x.copy() for _ in range(n + 1)]
        self.step = step
        self.s_end = n * step
        self.S = [k * step for k in range(n + 1)]
        self._route: Route | None = None

    def extend(self, p: np.ndarray, z: np.ndarray | None = None) -> None:
        """Append the tip position ``p`` (m) once it is >= ``step`` past the last point.

        With the tip's view direction ``z``, only the advance along it counts (for the test and as the arc
        length added): a bent tip swept sideways by a roll moves the tip, not the shaft, so the shaft's arc
        length stays in step with the insertion instead of running ahead of it by the sweep.
        """
        d = np.linalg.norm(p - self.P[-1])
        ds = d if z is None else float((p - self.P[-1]) @ z)
        if ds < self.step:
            return
        t = (p - self.P[-1]) / d
        x = self.X[-1] - (self.X[-1] @ t) * t
        nx = np.linalg.norm(x)
        if nx < 1e-6:
            return
        self.P.append(p.copy())
        self.X.append(x / nx)
        self.S.append(self.S[-1] + ds)
        self.s_end += ds
        self._route = None

    @property
    def route(self) -> Route:
        if self._route is None:
            P = np.array(self.P)
            X = np.array(self.X)
            s = np.array(self.S)
            R = np.zeros((len(P), 3, 3))
            R[:, :, 0] = X
            self._route = Route(P, s, R)
        return self._route


class LumenShaft:
    """The passive shaft conforming to the lumen: the bending segment's base slides along the airway's
    centreline from the trachea to the branch the tip is in (``shaft: lumen``).

    A real bronchoscope's insertion tube is passive and flexible: pushed through the airway, the walls
    bend it along the lumen, and only the tip's bending section is steered.  Modelled kinematically, as the
    ``trace`` shaft: its path is the centreline polyline root -> the tip's current branch (nearest
    centreline point, :meth:`Airways.locate`), resampled every ``step`` m and smoothed (Gaussian, ``sigma``
    m: the graph's joints have kinks a shaft does not make), with a rotation-minimising frame started from
    the start pose's x.  Any two such paths share their frames up to ~4 ``sigma`` before the fork, and the
    base is ``l`` behind the tip, so a change of branch does not move the base.  The shaft is the world's
    (physics), not the policy's: the policy still sees only images.  ``s_end``: the tip's arclength along
    the path (m).
    """

    def __init__(self, airways: Airways, pose: np.ndarray, step: float = 1e-3, sigma: float = 3e-3) -> None:
        self.airways, self.step, self.sigma = airways, step, sigma
        self.x0 = pose[:3, 0].copy()
        self.branch = airways.graph.root.id
        self._cache: dict[int, Route] = {}
        self.s_end = self._arclength(pose[:3, 3])

    def _build(self, branch: int) -> Route:
        if branch not in self._cache:
            P, s = self.airways.route_polyline(branch)
            n = int(s[-1] / self.step) + 1
            si = np.arange(n) * self.step
            Q = np.stack([np.interp(si, s, P[:, k]) for k in range(3)], axis=1)
            Q = ndimage.gaussian_filter1d(Q, self.sigma / self.step, axis=0, mode="nearest")
            si = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Q, axis=0), axis=1))])
            keep = np.concatenate([[True], np.diff(si) > 1e-9])
            Q, si = Q[keep], si[keep]
            t = np.gradient(Q, si, axis=0)
            t /= np.linalg.norm(t, axis=1, keepdims=True)
            X = np.zeros_like(Q)
            x = self.x0 - (self.x0 @ t[0]) * t[0]
            for i in range(len(Q)):
                x = x - (x @ t[i]) * t[i]
                x = x / np.linalg.norm(x)
                X[i] = x
            R = np.zeros((len(Q), 3, 3))
            R[:, :, 0] = X
            self._cache[branch] = Route(Q, si, R)
        return self._cache[branch]

    def _arclength(self, p: np.ndarray) -> float:
        r = self._build(self.branch)
        return float(r.s[int(np.argmin(np.linalg.norm(r.P - p, axis=1)))])

    def extend(self, p: np.ndarray, z: np.ndarray | None = None) -> None:
        """Follow the tip at ``p`` (m) into its branch (``z`` unused: the lumen, not the tip, shapes the shaft)."""
        self.branch = self.airways.locate(p)[0]
        self.s_end = self._arclength(p)

    @property
    def route(self) -> Route:
        return self._build(self.branch)


