"""TotalSegmentator's nnU-Net v2 path (anatomy.nnunet, segment.method=totalsegmentator) end to end, without weights.

A tiny randomly initialised ``PlainConvUNet`` (the class of TotalSegmentator's models) is saved in nnU-Net's
results layout (``Dataset258_lung_vessels_248subj/nnUNetTrainer__nnUNetPlans__3d_fullres/{plans.json,
dataset.json, fold_0/checkpoint_final.pth}``) in tmp_path, in the plans format of nnU-Net >= 2.4 and in the older
one TotalSegmentator's weights use; the segment code loads and runs it as it would the real weights, and the
result is compared with the network applied directly (torch, no pipeline code).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

torch = pytest.importorskip("torch", reason="the 'ml' extra (local CPU torch wheel) is not installed")
pytest.importorskip("dynamic_network_architectures",
                    reason="dynamic-network-architectures (extra 'totalseg') is not installed")

from dynamic_network_architectures.architectures.unet import PlainConvUNet  # noqa: E402

from room_pipeline.anatomy import nnunet  # noqa: E402
from room_pipeline.anatomy import segment as seg  # noqa: E402
from room_pipeline.anatomy.segment import SegmentParams, segment_airways  # noqa: E402
from room_pipeline.errors import BackendUnavailable  # noqa: E402
from room_pipeline.io.volume import Volume  # noqa: E402

from .test_segment import synthetic_ct  # noqa: E402

LABELS = {"background": 0, "lung_vessels": 1, "lung_trachea_bronchia": 2}
PROPS = {"max": 200.0, "mean": -850.0, "median": -880.0, "min": -1100.0, "percentile_00_5": -1050.0,
         "percentile_99_5": 150.0, "std": 120.0}
ARCH = {"n_stages": 2, "features_per_stage": [4, 8], "conv_op": "torch.nn.modules.conv.Conv3d",
        "kernel_sizes": [[3, 3, 3], [3, 3, 3]], "strides": [[1, 1, 1], [2, 2, 2]], "n_conv_per_stage": [1, 1],
        "n_conv_per_stage_decoder": [1], "conv_bias": True,
        "norm_op": "torch.nn.modules.instancenorm.InstanceNorm3d", "norm_op_kwargs": {"eps": 1e-05, "affine": True},
        "dropout_op": None, "dropout_op_kwargs": None, "nonlin": "torch.nn.LeakyReLU",
        "nonlin_kwargs": {"inplace": True}}


def _network(seed: int = 0) -> PlainConvUNet:
    torch.manual_seed(seed)
    return PlainConvUNet(input_channels=1, n_stages=2, features_per_stage=[4, 8], conv_op=torch.nn.Conv3d,
                         kernel_sizes=[[3, 3, 3]] * 2, strides=[[1, 1, 1], [2, 2, 2]], n_conv_per_stage=[1, 1],
                         num_classes=3, n_conv_per_stage_decoder=[1], conv_bias=True, norm_op=torch.nn.InstanceNorm3d,
                         norm_op_kwargs={"eps": 1e-05, "affine": True}, nonlin=torch.nn.LeakyReLU,
                         nonlin_kwargs={"inplace": True}, deep_supervision=False).eval()


def _save_model(home: Path, net, patch, spacing, reader: str = "SimpleITKIO", legacy: bool = False) -> Path:
    """nnU-Net's results layout under ``home`` (TotalSegmentator's TOTALSEG_HOME_DIR); returns the model folder."""
    folder = home / "nnunet" / "results" / seg.TS_DATASET / "nnUNetTrainer__nnUNetPlans__3d_fullres"
    (folder / "fold_0").mkdir(parents=True)
    cfg = {"data_identifier": "nnUNetPlans_3d_fullres", "preprocessor_name": "DefaultPreprocessor",
           "batch_size": 2, "patch_size": list(patch), "spacing": list(spacing),
           "normalization_schemes": ["CTNormalization"], "use_mask_for_norm": [False]}
    if legacy:  # nnU-Net < 2.4 keys (TotalSegmentator's weights)
        cfg.update(UNet_class_name="PlainConvUNet", UNet_base_num_features=4, unet_max_num_features=8,
                   n_conv_per_stage_encoder=[1, 1], n_conv_per_stage_decoder=[1],
                   conv_kernel_sizes=[[3, 3, 3], [3, 3, 3]], pool_op_kernel_sizes=[[1, 1, 1], [2, 2, 2]])
    else:
        cfg["architecture"] = {"network_class_name": "dynamic_network_architectures.architectures.unet.PlainConvUNet",
                               "arch_kwargs": ARCH, "_kw_requires_import": ["conv_op", "norm_op", "dropout_op", "nonlin"]}
    plans = {"dataset_name": seg.TS_DATASET, "plans_name": "nnUNetPlans", "image_reader_writer": reader,
             "transpose_forward": [0, 1, 2], "transpose_backward": [0, 1, 2], "configurations": {"3d_fullres": cfg},
             "foreground_intensity_properties_per_channel": {"0": PROPS}}
    (folder / "plans.json").write_text(json.dumps(plans))
    (folder / "dataset.json").write_text(json.dumps({"channel_names": {"0": "CT"}, "labels": LABELS,
                                                     "numTraining": 0, "file_ending": ".nii.gz"}))
    torch.save({"network_weights": net.state_dict(), "trainer_name": "nnUNetTrainer", "current_epoch": 0,
                "init_args": {"configuration": "3d_fullres", "fold": 0},
                "logging": {"train_losses": [np.float64(0.5)]}, "inference_allowed_mirroring_axes": (0, 1, 2)},
               folder / "fold_0" / "checkpoint_final.pth")
    return folder


@pytest.fixture(scope="module")
def small_ct():
    """The synthetic chest CT (1 mm) cropped around its trachea: 48 x 40 x 56 voxels, (x, y, z) RAS+."""
    ct, _, _ = synthetic_ct(30.0, 0)
    c = np.array(np.nonzero(ct.data < -900)).mean(axis=1).astype(int)
    lo = np.maximum(c - [24, 20, 28], 0)
    sub = ct.data[lo[0]:lo[0] + 48, lo[1]:lo[1] + 40, lo[2]:lo[2] + 56]
    aff = ct.affine.copy()
    aff[:3, 3] = ct.index_to_world(lo[None].astype(float))[0]
    return Volume(np.ascontiguousarray(sub), aff)


def _direct(net, data_xyz: np.ndarray, reader: str) -> np.ndarray:
    """The network on the whole normalised volume as one tile (no pipeline code): labels in (x, y, z)."""
    x = data_xyz.astype(np.float32)
    x = np.transpose(x, (2, 1, 0)) if reader == "SimpleITKIO" else x
    x = (np.clip(x, PROPS["percentile_00_5"], PROPS["percentile_99_5"]) - PROPS["mean"]) / PROPS["std"]
    with torch.inference_mode():
        out = net(torch.from_numpy(np.ascontiguousarray(x))[None, None])[0].numpy()
    lab = np.argmax(out, axis=0)
    return np.transpose(lab, (2, 1, 0)) if reader == "SimpleITKIO" else lab


@pytest.mark.parametrize("legacy", [False, True], ids=["plans_v2.4", "plans_legacy"])
@pytest.mark.parametrize("reader", ["SimpleITKIO", "NibabelIO"])
def test_segment_runs_a_random_plainconvunet_from_the_nnunet_layout(tmp_path, small_ct, reader, legacy):
    """One tile covering the volume at the plans' spacing: the pipeline's labels == the network applied directly."""
    net = _network(0)
    shape = small_ct.shape[::-1] if reader == "SimpleITKIO" else small_ct.shape
    spacing = (small_ct.spacing / 1e-3)[::-1] if reader == "SimpleITKIO" else small_ct.spacing / 1e-3
    _save_model(tmp_path, net, shape, spacing, reader, legacy)
    model = nnunet.load_model(nnunet.find_model_folder(tmp_path / "nnunet" / "results" / seg.TS_DATASET))
    assert isinstance(model.network, PlainConvUNet) and model.label("lung_trachea_bronchia") == 2
    affine_mm = small_ct.affine.copy()
    affine_mm[:3, :] /= 1e-3
    labels = nnunet.predict_volume(model, small_ct.data.astype(np.float32), affine_mm)
    ref = _direct(net, np.asarray(small_ct.data), reader)
    assert labels.shape == small_ct.shape
    agree = float((labels == ref).mean())
    assert agree == 1.0, f"labels agree with the direct forward pass on {agree:.4f} of the voxels"
    assert len(np.unique(ref)) >= 2  # the random network does not predict one class everywhere

    # through segment_airways: the airway class (by its dataset.json name), largest 26-connected piece
    if not (ref == 2).any():
        pytest.skip("the random network predicts no airway voxel")
    res = segment_airways(small_ct, SegmentParams(method="totalsegmentator", weights_dir=str(tmp_path)))
    lab, n = ndi.label(ref == 2, np.ones((3, 3, 3)))
    biggest = lab == (1 + int(np.argmax(np.bincount(lab.ravel())[1:])))
    assert np.array_equal(res.mask.data.astype(bool), biggest)
    assert res.report["method"] == "totalsegmentator" and res.report["airway_label"] == 2
    assert res.report["components"] == n and res.mask.data[res.seed] == 1


def test_sliding_window_resampling_and_orientation(tmp_path, small_ct):
    """Several tiles, resampling to another spacing, and an input stored with a flipped, permuted axis order:
    the labels follow the anatomy (same world labels), and two runs give the same bytes."""
    net = _network(1)
    _save_model(tmp_path, net, (24, 24, 24), (1.3, 1.3, 1.3), "SimpleITKIO")
    model = nnunet.load_model(nnunet.find_model_folder(tmp_path / "nnunet" / "results" / seg.TS_DATASET))
    affine_mm = small_ct.affine.copy()
    affine_mm[:3, :] /= 1e-3
    data = small_ct.data.astype(np.float32)
    a = nnunet.predict_volume(model, data, affine_mm)
    assert a.shape == data.shape and set(np.unique(a)) <= {0, 1, 2}
    assert np.array_equal(a, nnunet.predict_volume(model, data, affine_mm))
    # the same image stored as (z, y, x) with x flipped (LAS-like, a different voxel order)
    perm = np.transpose(data, (2, 1, 0))[:, :, ::-1]
    A = affine_mm[:, [2, 1, 0, 3]].copy()
    A[:3, 3] += A[:3, 2] * (data.shape[0] - 1)
    A[:3, 2] *= -1
    b = nnunet.predict_volume(model, np.ascontiguousarray(perm), A)
    assert np.array_equal(np.transpose(b[:, :, ::-1], (2, 1, 0)), a)
    assert nnunet.window_starts(30, 24, 0.5) == [0, 6] and nnunet.window_starts(24, 24, 0.5) == [0]
    assert nnunet.window_starts(100, 24, 0.5) == [0, 11, 22, 33, 43, 54, 65, 76]   # ceil(76 / 12) + 1 tiles


def test_bad_model_folders_are_one_line_errors(tmp_path, small_ct):
    net = _network(0)
    folder = _save_model(tmp_path, net, (48, 40, 56), (1.0, 1.0, 1.0), "NibabelIO")
    # weights of another network
    other = PlainConvUNet(1, 2, [4, 16], torch.nn.Conv3d, 3, [1, 2], [1, 1], 3, [1], True, torch.nn.InstanceNorm3d,
                          {"eps": 1e-5, "affine": True}, None, None, torch.nn.LeakyReLU, {"inplace": True})
    torch.save({"network_weights": other.state_dict()}, folder / "fold_0" / "checkpoint_final.pth")
    with pytest.raises(BackendUnavailable, match="do not fit") as ei:
        nnunet.load_model(folder)
    assert "\n" not in str(ei.value)
    # a plans file naming a class outside the network packages is refused, not imported
    plans = json.loads((folder / "plans.json").read_text())
    plans["configurations"]["3d_fullres"]["architecture"]["network_class_name"] = "os.system"
    (folder / "plans.json").write_text(json.dumps(plans))
    with pytest.raises(BackendUnavailable, match="only dynamic_network_architectures"):
        nnunet.load_model(folder)
    (folder / "fold_0" / "checkpoint_final.pth").unlink()
    with pytest.raises(BackendUnavailable, match="checkpoint_final.pth missing"):
        nnunet.load_model(folder)
    with pytest.raises(BackendUnavailable, match="no nnU-Net model folder"):
        nnunet.find_model_folder(tmp_path / "nowhere")
