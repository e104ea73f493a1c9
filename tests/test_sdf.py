"""Tests of room_pipeline.anatomy.sdf (mask -> sub-voxel signed distance) and evaluate.surface.sdf_error."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.evaluate.surface import sdf_error
from room_pipeline.io.volume import Volume

ROOT = Path(__file__).resolve().parents[1]


def small_tree() -> AirwayTree:
    """Trachea + 2 main bronchi + 4 lobar-like branches (radii 3.5 .. 1.2 mm)."""
    mm = 1e-3
    b = [Branch(0, -1, 0, [0, 0, 0], [0, 0, -20 * mm], 3.5 * mm)]
    e = b[0].end
    b.append(Branch(1, 0, 1, e, e + np.array([12, 3, -12]) * mm, 2.5 * mm))
    b.append(Branch(2, 0, 1, e, e + np.array([-10, -4, -14]) * mm, 2.2 * mm))
    for pid, nid in ((1, 3), (2, 5)):
        p = b[pid].end
        s = 1 if pid == 1 else -1
        b.append(Branch(nid, pid, 2, p, p + np.array([s * 9, 6, -6]) * mm, 1.6 * mm))
        b.append(Branch(nid + 1, pid, 2, p, p + np.array([s * 4, -7, -10]) * mm, 1.2 * mm))
    return AirwayTree(b)


def grid_for(tree: AirwayTree, spacing, margin=4e-3, lo=None, hi=None) -> Volume:
    return tree.rasterise(spacing, margin, lo, hi)[0]


def true_mask_and_sdf(tree: AirwayTree, grid: Volume) -> tuple[Volume, Volume]:
    """Ground truth on ``grid`` (made by :func:`grid_for`)."""
    lo = grid.index_to_world(np.zeros((1, 3)))[0]
    hi = grid.index_to_world(np.array(grid.shape, float)[None] - 1)[0]
    return tree.rasterise(grid.spacing, lo=lo, hi=hi)


@pytest.fixture(scope="module")
def tree() -> AirwayTree:
    return small_tree()


# ------------------------------------------------------------------ config
def test_params_match_yaml_and_reject_unknown_keys():
    cfg = yaml.safe_load((ROOT / "conf" / "sdf" / "default.yaml").read_text())
    assert set(cfg) == {f.name for f in dataclasses.fields(SdfParams)}
    assert SdfParams.from_dict(cfg) == SdfParams()
    with pytest.raises(ConfigError, match="sdf.bogus"):
        SdfParams.from_dict({**cfg, "bogus": 1})
    with pytest.raises(ConfigError):
        SdfParams.from_dict({"method": "magic"})
    with pytest.raises(ConfigError):
        SdfParams.from_dict({"band_mm": "wide"})


# ------------------------------------------------------------------ accuracy
@pytest.mark.parametrize("spacing", [0.7e-3, (0.6e-3, 0.7e-3, 1.1e-3)], ids=["iso", "aniso"])
def test_subvoxel_accuracy_against_analytic_tree(tree, spacing):
    mask, _ = true_mask_and_sdf(tree, grid_for(tree, spacing))
    sdf = compute_sdf(mask, SdfParams())
    assert sdf.data.dtype == np.float32 and sdf.shape == mask.shape
    np.testing.assert_allclose(sdf.affine, mask.affine)
    e = sdf_error(sdf, tree, band=3e-3)
    assert e["n"] > 10_000
    assert e["mae_vox"] <= 0.25, e
    assert e["sign_mismatch"] == 0.0
    # and clearly better than the half-voxel-corrected EDT baseline
    base = sdf_error(compute_sdf(mask, SdfParams(method="edt_halfvoxel")), tree, band=3e-3)
    assert e["mae_vox"] < 0.8 * base["mae_vox"]
    plain = sdf_error(compute_sdf(mask, SdfParams(method="edt")), tree, band=3e-3)
    assert plain["mae_vox"] > e["mae_vox"]


def test_sdf_error_known_offset(tree):
    _, true = true_mask_and_sdf(tree, grid_for(tree, 1e-3))
    e0 = sdf_error(true, tree, band=2e-3)
    assert e0["mae_m"] < 1e-7
    e1 = sdf_error(true.with_data(true.data + np.float32(2e-4)), tree, band=2e-3)
    assert e1["mae_m"] == pytest.approx(2e-4, rel=1e-3)
    assert e1["mae_vox"] == pytest.approx(0.2, rel=1e-3)
    assert e1["bias_m"] == pytest.approx(2e-4, rel=1e-3)


# ------------------------------------------------------------------ hard cases
def _vol(data, spacing=0.7e-3):
    aff = np.diag([spacing, spacing, spacing, 1.0])
    return Volume(data, aff)


def test_empty_mask_raises():
    with pytest.raises(InputError, match="empty"):
        compute_sdf(_vol(np.zeros((20, 20, 20), np.uint8)), SdfParams())


def test_one_voxel_wide_airways_survive():
    m = np.zeros((40, 40, 40), bool)
    m[20, 20, 5:35] = True                                # axis-aligned line
    i = np.arange(5, 35)
    m[i, i, 30] = True                                    # diagonal in-plane line (edge-connected)
    m[i, 34 - i + 5, 8] = True
    s = compute_sdf(_vol(m.astype(np.uint8)), SdfParams()).data
    h = 0.7e-3
    assert np.all(s[m] < 0)
    assert np.all(s[~m] > 0)
    # thin: the radius estimate at the line is under one voxel
    assert np.all(s[m] > -h)
    # zero level exists between the line and its neighbours
    assert s[21, 20, 20] > 0 and s[20, 20, 20] < 0


def test_branches_one_voxel_apart_stay_separate():
    m = np.zeros((40, 40, 40), bool)
    c = np.indices(m.shape)
    r2 = (c[0] - 20) ** 2
    m |= ((c[1] - 15) ** 2 + r2 < 3.5 ** 2)               # two parallel tubes along k
    m |= ((c[1] - 24) ** 2 + r2 < 3.5 ** 2)               # gap of one voxel column at j=19..20
    m[:, :, :3] = False
    m[:, :, -3:] = False
    gap = ~m[20, :, 20]
    assert gap[18:22].any()
    s = compute_sdf(_vol(m.astype(np.uint8)), SdfParams()).data
    assert np.all(s[m] < 0) and np.all(s[~m] > 0)
    from scipy import ndimage

    _, n = ndimage.label(s < 0)
    assert n == 2


def test_mask_touching_border_continues_the_airway():
    # a tube along k cut by both k faces of the volume: the SDF near the border is the tube's
    h = 0.7e-3
    tree = AirwayTree([Branch(0, -1, 0, [0, 0, -0.1], [0, 0, 0.1], 2.5e-3)])
    lo, hi = np.array([-5e-3, -5e-3, -6e-3]), np.array([5e-3, 5e-3, 6e-3])
    mask, true = true_mask_and_sdf(tree, grid_for(tree, h, lo=lo, hi=hi))
    assert mask.data[:, :, 0].any() and mask.data[:, :, -1].any()
    s = compute_sdf(mask, SdfParams())
    # the axis voxels at the border slices are ~radius deep, not capped by the border
    ax = np.argmin(np.abs(np.arange(mask.shape[0]) * h + lo[0]))
    assert s.data[ax, ax, 0] < -2e-3 and s.data[ax, ax, -1] < -2e-3
    e = sdf_error(s, tree, band=2e-3)
    assert e["mae_vox"] < 0.25


# ------------------------------------------------------------------ properties
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.booleans())
def test_sign_and_gradient_property(seed, sphere):
    rng = np.random.default_rng(seed)
    mm = 1e-3
    if sphere:
        c = rng.uniform(-1, 1, 3) * mm
        tree = AirwayTree([Branch(0, -1, 0, c, c, rng.uniform(2, 5) * mm)])
    else:
        p0 = np.zeros(3)
        p1 = p0 + rng.normal(size=3) * 6 * mm
        p2 = p1 + rng.normal(size=3) * 5 * mm
        tree = AirwayTree([Branch(0, -1, 0, p0, p1, rng.uniform(1.5, 3) * mm),
                           Branch(1, 0, 1, p1, p2, rng.uniform(0.8, 2) * mm)])
    h = rng.uniform(0.5, 0.9) * mm
    mask, true = true_mask_and_sdf(tree, grid_for(tree, h, margin=3 * mm))
    s = compute_sdf(mask, SdfParams()).data.astype(np.float64)
    m = mask.data > 0
    # sign agrees with the mask at every voxel centre away from the boundary layer
    away = np.abs(true.data) > 0.5 * h
    assert np.all((s[away] < 0) == m[away])
    # in fact the sign agrees everywhere (constrained surface)
    assert np.all((s < 0) == m)
    # |grad sdf| ~ 1 away from the medial axis and the border
    g = np.gradient(s, h)
    gn = np.sqrt(sum(gi ** 2 for gi in g))
    sel = (np.abs(true.data) > 1.5 * h) & (np.abs(true.data) < 2.5 * mm)
    r = float(min(b.radius for b in tree.branches))
    sel &= true.data > -(r - 1.5 * h)          # not at the medial axis
    inner = np.zeros_like(sel)
    inner[2:-2, 2:-2, 2:-2] = True
    sel &= inner
    if sel.sum() > 50:
        assert np.median(np.abs(gn[sel] - 1)) < 0.05
        assert np.percentile(np.abs(gn[sel] - 1), 90) < 0.2


@pytest.mark.parametrize("dtype,scale", [(np.float32, True), (np.uint8, False), (np.float64, False), (np.int16, False)])
@pytest.mark.parametrize("ext", [".nii", ".nii.gz"])
def test_streamed_nifti_writer_gives_nibabels_bytes(tmp_path, dtype, scale, ext):
    """write_nifti streams the data slab by slab (memory, issue #18 item 4): same bytes as nibabel's to_bytes."""
    import gzip

    import nibabel as nib

    from room_pipeline.io.volume import _m_to_mm, write_nifti

    d = (np.random.default_rng(0).random((7, 5, 9)) * 10).astype(dtype)
    aff = np.diag([5e-4, 6e-4, 7e-4, 1.0])
    aff[:3, 3] = [0.01, -0.02, 0.03]
    p = tmp_path / f"a{ext}"
    write_nifti(p, Volume(d, aff), description="x", scale_values_to_mm=scale)
    got = p.read_bytes()
    if ext == ".nii.gz":
        got = gzip.decompress(got)
    img = nib.Nifti1Image((d.astype(np.float64) / 1e-3).astype(np.float32) if scale else d, _m_to_mm(aff))
    img.set_qform(img.affine, code=1)
    img.set_sform(img.affine, code=1)
    img.header.set_xyzt_units(xyz="mm", t="sec")
    img.header["descrip"] = b"x"
    assert got == img.to_bytes()
