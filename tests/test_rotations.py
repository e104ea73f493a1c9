"""geometry/rotations.py: the plain-NumPy rotation helpers the simulation and its PyBullet adapter share."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from room_pipeline.geometry.rotations import log_so3, log_so3_batch, mat_to_quat, rx, ry, rz


def test_mat_to_quat_agrees_with_scipy_but_not_bit_for_bit():
    """The reason the module keeps its own conversion (see its docstring): scipy's differs in the last bits."""
    R = Rotation.random(1000, random_state=0).as_matrix()
    a = np.array([mat_to_quat(r) for r in R])
    b = Rotation.from_matrix(R).as_quat()
    b = np.where((a * b).sum(1, keepdims=True) < 0, -b, b)      # q and -q are the same rotation
    assert np.abs(a - b).max() < 1e-12
    assert (a != b).any(axis=1).sum() > 0          # 685 of these 1,000 with scipy 1.x here


def test_mat_to_quat_every_branch_and_identity():
    for R in (np.eye(3), rx(math.pi), ry(math.pi), rz(math.pi), rx(0.3) @ rz(2.9)):
        q = np.array(mat_to_quat(R))
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        assert np.allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-12)


def test_log_so3_small_half_turn_and_batch():
    assert np.allclose(log_so3(np.eye(3)), 0.0)
    assert np.allclose(log_so3(rz(1e-8)), [0.0, 0.0, 1e-8], atol=1e-20)
    v = log_so3(rx(math.pi))
    assert np.isclose(np.linalg.norm(v), math.pi) and np.allclose(np.abs(v) / math.pi, [1.0, 0.0, 0.0])
    R = np.stack([rx(0.2) @ ry(-0.4), rz(math.pi), np.eye(3), rz(1e-9)])
    ref = Rotation.from_matrix(R).as_rotvec()
    got = log_so3_batch(R)
    assert np.allclose(np.abs(got[1]), np.abs(ref[1]))        # half turn: the axis' sign is arbitrary
    assert np.allclose(np.delete(got, 1, 0), np.delete(ref, 1, 0), atol=1e-12)
