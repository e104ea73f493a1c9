"""Airway segmentation (room_pipeline.anatomy.segment): accuracy, hard cases, errors, config."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage as ndi

from room_pipeline.anatomy import region_growing
from room_pipeline.anatomy import segment as seg
from room_pipeline.anatomy.segment import (SegmentParams, SegmentResult, find_trachea_seed,
                                           segment_airways, validate_mask)
from room_pipeline.anatomy.tree import AirwayTree, Branch
from room_pipeline.errors import BackendUnavailable, ConfigError, InputError
from room_pipeline.evaluate.segmentation import segmentation_metrics
from room_pipeline.io.volume import Volume

MM = 1e-3
CONF = Path(__file__).resolve().parents[1] / "conf" / "segment"
TARGETS = {"dice": 0.90, "precision": 0.95, "tree_length_detected": 0.85, "branches_detected": 0.80}


# ----------------------------------------------------------------------------- synthetic CT
def synthetic_tree() -> AirwayTree:
    """Trachea + 2 main bronchi + 4 lobar + 8 segmental branches (radii 8 / 5.5 / 3.5 / 2 mm)."""
    P = lambda *v: np.array(v, dtype=float) * MM  # noqa: E731
    bs = [Branch(0, -1, 0, P(0, 0, 70), P(0, 0, 10), 8 * MM, "trachea")]
    for sx in (1, -1):
        mb_end = P(28 * sx, 0, -15)
        m = len(bs)
        bs.append(Branch(m, 0, 1, P(0, 0, 10), mb_end, 5.5 * MM))
        for dy, ez in ((12, -42), (-12, -45)):
            e2 = P(40 * sx, dy, ez)
            c = len(bs)
            bs.append(Branch(c, m, 2, mb_end, e2, 3.5 * MM))
            for ddx, ddz in ((10, -12), (-4, -16)):
                bs.append(Branch(len(bs), c, 3, e2, e2 + P(ddx * sx, dy * 0.6, ddz), 2.0 * MM))
    return AirwayTree(bs)


def _capsule_field(tree: AirwayTree, shape, affine, grow: float) -> np.ndarray:
    """min over branches of |p - axis| - radius * (1 + grow) (metres), per branch in its box only."""
    sp = np.diag(affine)[:3]
    org = affine[:3, 3]
    d = np.full(shape, np.inf, dtype=np.float32)
    axes = [org[a] + sp[a] * np.arange(shape[a]) for a in range(3)]
    for b in tree.branches:
        r = b.radius * (1 + grow) + 2 * float(sp.max())
        lo = np.maximum(np.floor((np.minimum(b.start, b.end) - r - org) / sp).astype(int), 0)
        hi = np.minimum(np.ceil((np.maximum(b.start, b.end) + r - org) / sp).astype(int) + 1, shape)
        if np.any(hi <= lo):
            continue
        px, py, pz = (axes[a][lo[a]:hi[a]] - b.start[a] for a in range(3))
        px, py, pz = px[:, None, None], py[None, :, None], pz[None, None, :]
        ab = b.end - b.start
        t = np.clip((px * ab[0] + py * ab[1] + pz * ab[2]) / (ab @ ab), 0, 1)
        dist = np.sqrt((px - t * ab[0]) ** 2 + (py - t * ab[1]) ** 2 + (pz - t * ab[2]) ** 2) - b.radius * (1 + grow)
        sl = tuple(slice(lo[a], hi[a]) for a in range(3))
        d[sl] = np.minimum(d[sl], dist)
    return d


def synthetic_ct(noise_hu: float = 30.0, seed: int = 0, spacing_mm=(1.0, 1.0, 1.0), psf_mm: float = 0.6,
                 z_top_mm: float = 80.0, tree: AirwayTree | None = None):
    """(ct, ground-truth mask, tree): lumen -1000 HU, wall +40 HU of 0.15 x diameter, parenchyma -850,
    soft-tissue body in outside air, Gaussian PSF then white noise.  Axis-aligned RAS+ grid."""
    tree = tree or synthetic_tree()
    sp = np.asarray(spacing_mm, dtype=float)
    lo, hi = np.array([-65.0, -45.0, -70.0]), np.array([65.0, 45.0, z_top_mm])
    shape = tuple(int(v) for v in np.floor((hi - lo) / sp) + 1)
    aff = np.eye(4)
    aff[:3, :3] = np.diag(sp * MM)
    aff[:3, 3] = lo * MM
    x, y, z = np.meshgrid(*[lo[a] + sp[a] * np.arange(shape[a]) for a in range(3)], indexing="ij", sparse=True)
    ct = np.full(shape, -1000.0, dtype=np.float32)
    ct[np.broadcast_to((x / 64) ** 2 + (y / 44) ** 2 <= 1, shape)] = 40.0
    ct[np.broadcast_to(((x / 60) ** 2 + (y / 40) ** 2 <= 1) & (z < 35) & (z > -68), shape)] = -850.0
    lumen = _capsule_field(tree, shape, aff, 0.0) < 0
    ct[_capsule_field(tree, shape, aff, 0.3) < 0] = 40.0
    ct[lumen] = -1000.0
    if psf_mm > 0:
        ct = ndi.gaussian_filter(ct, psf_mm / sp)
    ct += np.random.default_rng(seed).normal(0.0, noise_hu, shape).astype(np.float32)
    return Volume(np.rint(ct).astype(np.int16), aff), Volume(lumen.astype(np.uint8), aff.copy()), tree


def _check_targets(m: dict) -> None:
    for k, v in TARGETS.items():
        assert m[k] >= v, f"{k}={m[k]:.3f} < {v} ({ {kk: round(m[kk], 3) for kk in TARGETS} })"


@pytest.fixture(scope="module")
def synth30():
    return synthetic_ct(30.0, 0)


# ----------------------------------------------------------------------------- params / config
def test_params_defaults_equal_region_growing_yaml():
    d = yaml.safe_load((CONF / "region_growing.yaml").read_text())
    assert SegmentParams.from_dict(d) == SegmentParams()
    fields = {f.name for f in dataclasses.fields(SegmentParams)}
    ts = yaml.safe_load((CONF / "totalsegmentator.yaml").read_text())
    assert set(d) | set(ts) == fields
    assert SegmentParams.from_dict(ts).method == "totalsegmentator"


def test_params_reject_unknown_and_invalid():
    with pytest.raises(ConfigError, match="thresold_max_hu"):
        SegmentParams.from_dict({"thresold_max_hu": -500})
    with pytest.raises(ConfigError, match="method"):
        SegmentParams.from_dict({"method": "magic"})
    with pytest.raises(ConfigError, match="connectivity"):
        SegmentParams.from_dict({"connectivity": 18})
    with pytest.raises(ConfigError, match="leak_factor"):
        SegmentParams.from_dict({"leak_factor": "x"})
    assert SegmentParams.from_dict({"refine_hu": None, "leak_factor": 2}).leak_factor == 2.0


# ----------------------------------------------------------------------------- accuracy
@pytest.mark.parametrize("noise", [30.0, 80.0])
@pytest.mark.parametrize("rng_seed", [0, 1, 2])
def test_synthetic_tree_meets_targets(noise, rng_seed):
    ct, gt, tree = synthetic_ct(noise, rng_seed)
    res = segment_airways(ct, SegmentParams())
    assert isinstance(res, SegmentResult)
    assert res.mask.data.dtype == np.uint8 and set(np.unique(res.mask.data)) <= {0, 1}
    assert res.mask.data[res.seed] == 1
    _check_targets(segmentation_metrics(res.mask, gt, tree))


def test_seed_is_in_trachea(synth30):
    ct, _, tree = synth30
    seed = find_trachea_seed(ct, SegmentParams())
    p = ct.index_to_world(np.array([seed]))
    tr = tree.branch(0)
    assert AirwayTree([tr]).contains(p)[0]
    assert p[0, 2] > 40 * MM  # in the superior part


def test_report_is_json_serialisable(synth30):
    import json

    ct, _, _ = synth30
    res = segment_airways(ct)
    rep = json.loads(json.dumps(res.report))
    assert rep["voxels"] == int(res.mask.data.sum())
    assert rep["volume_m3"] == pytest.approx(rep["voxels"] * float(np.prod(ct.spacing)))
    assert rep["leak_detected"] is True and rep["threshold_hu"] == res.threshold_hu
    ts = [h[0] for h in rep["threshold_history"]]
    assert ts == sorted(ts) and res.threshold_hu in ts


def test_trachea_cut_by_volume_border():
    ct, gt, tree = synthetic_ct(30.0, 1, z_top_mm=45.0)  # trachea (z 70 -> 10 mm) leaves through the top face
    res = segment_airways(ct)
    assert res.mask.data[:, :, -1].any()  # the lumen reaches the top face
    _check_targets(segmentation_metrics(res.mask, gt, tree))


def test_anisotropic_spacing():
    ct, gt, tree = synthetic_ct(30.0, 2, spacing_mm=(0.6, 0.6, 1.2))
    res = segment_airways(ct)
    _check_targets(segmentation_metrics(res.mask, gt, tree))


def test_any_voxel_orientation(synth30):
    """Axes permuted and the superior axis flipped (affine adjusted): same segmentation."""
    ct, gt, tree = synth30
    perm = (2, 0, 1)
    data = np.transpose(ct.data, perm)[::-1]  # new axis 0 = old k (superior), reversed
    A = ct.affine[:, list(perm) + [3]].copy()
    n0 = data.shape[0]
    A[:3, 3] += A[:3, 0] * (n0 - 1)
    A[:3, 0] *= -1
    ct2 = Volume(np.ascontiguousarray(data), A)
    assert ct2.superior_axis() == (0, -1)
    assert np.allclose(ct2.index_to_world(np.array([[0, 0, 0]])), ct.index_to_world(np.array([[0, 0, n0 - 1]])))
    r1, r2 = segment_airways(ct), segment_airways(ct2)
    back = np.transpose(r2.mask.data[::-1], np.argsort(perm))
    dice = 2 * np.sum(back & r1.mask.data) / (back.sum() + r1.mask.data.sum())
    assert dice > 0.99
    gt2 = Volume(np.ascontiguousarray(np.transpose(gt.data, perm)[::-1]), A)
    _check_targets(segmentation_metrics(r2.mask, gt2, tree))


# ----------------------------------------------------------------------------- topology hard cases
def _block_ct(shape=(60, 60, 80)) -> np.ndarray:
    """Soft-tissue block (+40 HU) in a 3-voxel rim of outside air."""
    ct = np.full(shape, 40.0, dtype=np.float32)
    ct[:3], ct[-3:], ct[:, :3], ct[:, -3:] = -1000, -1000, -1000, -1000
    return ct


def _trachea(ct: np.ndarray, z0: int, r: float = 8.0) -> None:
    i, j = np.ogrid[:ct.shape[0], :ct.shape[1]]
    disc = (i - 30) ** 2 + (j - 30) ** 2 <= r * r
    ct[:, :, z0:][disc] = -1000


def test_one_voxel_airway_is_kept():
    ct = _block_ct()
    _trachea(ct, 40)
    ct[30, 30, 20:41] = -1000        # one-voxel-wide airway hanging from the trachea ...
    ct[30:50, 30, 20] = -1000        # ... turning sideways
    res = segment_airways(Volume(ct.astype(np.int16), np.diag([MM, MM, MM, 1.0])))
    m = res.mask.data
    assert m[30, 30, 20:41].all() and m[30:50, 30, 20].all()
    assert m.sum() == np.count_nonzero(ct[3:-3, 3:-3] < -900)  # exactly the lumen, no rim


def test_branches_one_voxel_apart_are_not_merged():
    """A trachea splitting into two parallel tubes separated by a one-voxel septum."""
    ct = _block_ct()
    _trachea(ct, 15)
    ct[30, 3:-3, 15:50] = 40         # below z=50 a one-voxel septum splits it into two tubes
    rng = np.random.default_rng(0)
    noisy = ct + rng.normal(0, 30, ct.shape)
    res = segment_airways(Volume(np.rint(noisy).astype(np.int16), np.diag([MM, MM, MM, 1.0])))
    m = res.mask.data
    assert not m[30, :, 15:50].any()                 # septum never segmented
    for k in (18, 30, 45):                           # two separate lumens in every split slice
        lab, n = ndi.label(m[:, :, k])
        assert n == 2, (k, n)
    left, right = m[:30, :, 15:50].sum(), m[31:, :, 15:50].sum()
    assert left > 0.9 * np.count_nonzero(ct[3:30, 3:-3, 15:50] < -900)
    assert right > 0.9 * np.count_nonzero(ct[31:-3, 3:-3, 15:50] < -900)


def test_unconnected_neighbour_tube_stays_out():
    """A separate air tube one voxel from the trachea wall (not connected to it) is not segmented."""
    ct = _block_ct()
    _trachea(ct, 20, r=7)            # lumen reaches i=37 at j=30; i=38 is a one-voxel wall
    ct[39:42, 25:36, 20:75] = -1000  # the other tube: i = 39..41
    res = segment_airways(Volume(ct.astype(np.int16), np.diag([MM, MM, MM, 1.0])))
    m = res.mask.data
    assert m[30, 30, 40] == 1 and not m[38:43].any()


# ----------------------------------------------------------------------------- errors
@pytest.mark.parametrize("fill, msg", [(40.0, "no air"), (0.0, "no air"), (-1000.0, "all air")])
def test_uniform_volumes_raise(fill, msg):
    with pytest.raises(InputError, match=msg):
        segment_airways(Volume(np.full((20, 20, 20), fill, dtype=np.float32), np.diag([MM, MM, MM, 1.0])))


def test_no_trachea_raises():
    ct = _block_ct()
    ct[10:50, 10:50, 5:60] = -850    # lungs only, no airway
    ct[12:17, 12:17, 20:30] = -1000  # a small air pocket, too thin for a trachea
    with pytest.raises(InputError, match="no trachea found"):
        segment_airways(Volume(ct.astype(np.int16), np.diag([MM, MM, MM, 1.0])))


def test_empty_result_raises(synth30):
    ct, _, _ = synth30
    p = SegmentParams(threshold_start_hu=-1300, threshold_max_hu=-1200, air_hu=-900)
    with pytest.raises(InputError, match="empty"):
        segment_airways(ct, p)


# ----------------------------------------------------------------------------- invariants
@settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(noise=st.floats(0, 80), rng_seed=st.integers(0, 2**16), radius=st.floats(6.0, 10.0),
       offset=st.floats(-10.0, 10.0))
def test_region_growing_invariants(noise, rng_seed, radius, offset):
    """Without refinement/cleanup the mask is exactly the seed's 6-component below the chosen threshold."""
    P = lambda *v: np.array(v) * MM  # noqa: E731
    tree = AirwayTree([Branch(0, -1, 0, P(offset, 0, 70), P(offset, 0, 10), radius * MM),
                       Branch(1, 0, 1, P(offset, 0, 10), P(offset + 30, 0, -20), 0.6 * radius * MM),
                       Branch(2, 0, 1, P(offset, 0, 10), P(offset - 30, 0, -20), 0.6 * radius * MM)])
    ct, _, _ = synthetic_ct(noise, rng_seed, spacing_mm=(1.5, 1.5, 1.5), tree=tree)
    p = SegmentParams(refine_hu=None, thin_airway_hu=None, fill_holes=False)
    res = segment_airways(ct, p)
    m = res.mask.data.astype(bool)
    smooth = region_growing._denoise(ct, p)
    assert m[res.seed]
    assert not (m & ~(smooth < res.threshold_hu)).any()          # subset of below-threshold voxels
    lab, n = ndi.label(m)
    assert n == 1                                                  # one component, containing the seed
    full = segment_airways(ct, SegmentParams()).mask.data.astype(bool)
    assert (full | m).sum() == full.sum()                          # cleanup only adds voxels
    assert ndi.label(full)[1] == 1


# ----------------------------------------------------------------------------- user masks
def test_validate_mask_keeps_largest_component():
    d = np.zeros((20, 20, 20), dtype=np.float32)
    d[2:10, 2:10, 2:10] = 3.0
    d[15:17, 15:17, 15:17] = 0.5
    d[12, 12, 12] = -1.0
    rep: dict = {}
    out = validate_mask(Volume(d, np.eye(4)), report=rep)
    assert out.data.dtype == np.uint8 and out.data.sum() == 512
    assert rep["dropped_components"] == 1 and rep["dropped_voxels"] == 8
    with pytest.raises(InputError, match="empty"):
        validate_mask(Volume(np.zeros((4, 4, 4)), np.eye(4)))


# ----------------------------------------------------------------------------- TotalSegmentator backend
def test_totalsegmentator_not_installed(monkeypatch, synth30):
    monkeypatch.setattr(seg.importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(BackendUnavailable, match="not installed") as ei:
        segment_airways(synth30[0], SegmentParams(method="totalsegmentator"))
    assert "\n" not in str(ei.value) and "region_growing" in str(ei.value)


def test_totalsegmentator_weights_missing(monkeypatch, tmp_path, synth30):
    monkeypatch.setattr(seg.importlib.util, "find_spec", lambda name, *a: object())
    monkeypatch.delenv("TOTALSEG_HOME_DIR", raising=False)
    with pytest.raises(BackendUnavailable, match="weights location not set"):
        segment_airways(synth30[0], SegmentParams(method="totalsegmentator"))
    with pytest.raises(BackendUnavailable, match="Dataset258_lung_vessels_248subj") as ei:
        segment_airways(synth30[0], SegmentParams(method="totalsegmentator", weights_dir=str(tmp_path)))
    assert "\n" not in str(ei.value) and "cannot be downloaded" in str(ei.value)


# the real call path (a randomly initialised PlainConvUNet in nnU-Net's layout): tests/test_nnunet.py


# ----------------------------------------------------------------------------- procedural phantom
REDUCED = {"spacing_mm": 1.2, "min_diameter_mm": 3.5, "lung_points": 4000}


@pytest.mark.parametrize("rng_seed", [0, 1, 2])
def test_phantom_reduced_meets_targets(rng_seed):
    phantom = pytest.importorskip("room_pipeline.anatomy.phantom")
    ph = phantom.make_phantom(phantom.PhantomParams.from_dict(REDUCED), rng_seed)
    res = segment_airways(ph.ct)
    _check_targets(segmentation_metrics(res.mask, ph.mask, ph.tree))


def test_phantom_trachea_cut_at_top():
    phantom = pytest.importorskip("room_pipeline.anatomy.phantom")
    ph = phantom.make_phantom(phantom.PhantomParams.from_dict({**REDUCED, "crop_top_mm": 30.0}), 0)
    res = segment_airways(ph.ct)
    _check_targets(segmentation_metrics(res.mask, ph.mask, ph.tree))


@pytest.mark.slow
@pytest.mark.parametrize("rng_seed", [0, pytest.param(1, marks=pytest.mark.exhaustive),
                                      pytest.param(2, marks=pytest.mark.exhaustive)])
def test_phantom_default_meets_targets(rng_seed):
    phantom = pytest.importorskip("room_pipeline.anatomy.phantom")
    ph = phantom.make_phantom(phantom.PhantomParams(), rng_seed)
    res = segment_airways(ph.ct)
    _check_targets(segmentation_metrics(res.mask, ph.mask, ph.tree))
