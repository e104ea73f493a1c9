"""Volume and mesh I/O: formats, frames, atomic writes, one-line errors."""
from __future__ import annotations

import gzip

import numpy as np
import pytest

from room_pipeline.errors import InputError
from room_pipeline.io.atomic import atomic_path, write_json
from room_pipeline.io.mesh import Mesh, read_obj, write_obj
from room_pipeline.io.volume import Volume, read_nifti_sdf, read_volume, write_nifti

from .conftest import shared_path


def _vol(shape=(5, 6, 7), spacing=(0.7e-3, 0.8e-3, 1.0e-3), dtype=np.int16):
    aff = np.diag([*spacing, 1.0])
    aff[:3, 3] = [-0.01, 0.02, 0.03]
    data = np.arange(np.prod(shape), dtype=dtype).reshape(shape)
    return Volume(data, aff)


def test_nifti_roundtrip_metres_and_mm(tmp_path):
    v = _vol()
    write_nifti(tmp_path / "a.nii.gz", v)
    w = read_volume(tmp_path / "a.nii.gz")
    np.testing.assert_array_equal(w.data, v.data)
    np.testing.assert_allclose(w.affine, v.affine, rtol=1e-6, atol=1e-9)
    import nibabel as nib
    img = nib.load(tmp_path / "a.nii.gz")
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(np.diag(img.affine)[:3], [0.7, 0.8, 1.0], rtol=1e-6)


def test_nifti_bytes_deterministic(tmp_path):
    v = _vol()
    write_nifti(tmp_path / "a.nii.gz", v)
    write_nifti(tmp_path / "b.nii.gz", v)
    assert (tmp_path / "a.nii.gz").read_bytes() == (tmp_path / "b.nii.gz").read_bytes()
    assert gzip.decompress((tmp_path / "a.nii.gz").read_bytes())  # valid gzip


def test_sdf_written_in_mm_read_in_metres(tmp_path):
    v = _vol(dtype=np.float32)
    sdf = v.with_data((v.data - 100).astype(np.float32) * 1e-4)
    write_nifti(tmp_path / "s.nii.gz", sdf, scale_values_to_mm=True)
    raw = read_volume(tmp_path / "s.nii.gz").data
    np.testing.assert_allclose(raw, sdf.data * 1e3, rtol=1e-6)
    np.testing.assert_allclose(read_nifti_sdf(tmp_path / "s.nii.gz").data, sdf.data, rtol=1e-6, atol=1e-12)


def test_world_index_roundtrip_and_superior_axis():
    v = _vol()
    ijk = np.array([[0, 0, 0], [1.5, 2.0, 3.25]])
    np.testing.assert_allclose(v.world_to_index(v.index_to_world(ijk)), ijk, atol=1e-12)
    assert v.superior_axis() == (2, 1)
    flipped = Volume(v.data, v.affine @ np.diag([1, 1, -1, 1]))
    assert flipped.superior_axis() == (2, -1)


def test_missing_unreadable_and_not_3d(tmp_path):
    with pytest.raises(InputError, match="input not found"):
        read_volume(tmp_path / "nope.nii.gz")
    bad = tmp_path / "bad.nii.gz"
    bad.write_bytes(b"not a nifti")
    with pytest.raises(InputError, match="cannot read volume"):
        read_volume(bad)
    import nibabel as nib
    nib.save(nib.Nifti1Image(np.zeros((4, 4), np.int16), np.eye(4)), tmp_path / "2d.nii.gz")
    with pytest.raises(InputError, match="3-D"):
        read_volume(tmp_path / "2d.nii.gz")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(InputError, match="unsupported"):
        read_volume(tmp_path / "x.txt")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(InputError, match="no DICOM"):
        read_volume(tmp_path / "emptydir")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("crash mid-write")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    write_json(target, {"a": np.float32(1.5), "b": np.arange(3)})
    assert target.read_text() == '{\n  "a": 1.5,\n  "b": [\n    0,\n    1,\n    2\n  ]\n}\n'


def test_obj_roundtrip(tmp_path):
    m = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 1e-3,
             np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    assert m.signed_volume() == pytest.approx(1e-9 / 6)
    write_obj(tmp_path / "m.obj", m, header="tetra")
    r = read_obj(tmp_path / "m.obj")
    np.testing.assert_allclose(r.vertices, m.vertices, atol=1e-12)
    np.testing.assert_array_equal(r.faces, m.faces)


def test_nrrd_lps_converted_to_ras():
    """The COPDGene NRRD is LPS; NIfTI-style RAS+ flips x and y."""
    path = shared_path("ct", "copdgene_ct64", "ct-64.nrrd")
    import SimpleITK as sitk
    img = sitk.ReadImage(str(path))
    v = read_volume(path)
    assert v.shape == img.GetSize()
    # the ITK physical point of voxel (1,2,3), LPS in mm, equals our RAS metres with x,y negated
    lps = np.array(img.TransformIndexToPhysicalPoint((1, 2, 3)))
    ras = v.index_to_world(np.array([[1, 2, 3]]))[0]
    np.testing.assert_allclose(ras * 1e3, lps * [-1, -1, 1], atol=1e-6)
    assert v.data.min() < -900  # HU


def test_dicom_series_folder_matches_nifti():
    folder = shared_path("ct", "totalseg_example", "dicom")
    v = read_volume(folder)
    assert v.data.ndim == 3 and v.shape[2] == len([p for p in folder.iterdir() if p.is_file()])
    assert np.all(v.spacing > 0) and v.data.min() < -500


def test_ply_roundtrip_and_open3d_reads_it(tmp_path):
    from room_pipeline.io.ply import read_ply, write_ply

    rng = np.random.default_rng(0)
    v = {"x": rng.normal(size=5), "y": rng.normal(size=5), "z": rng.normal(size=5),
         "radius": rng.random(5).astype(np.float32), "branch": np.arange(5, dtype=np.int32)}
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 4]])
    write_ply(tmp_path / "a.ply", v, edges, comments=("units: m",))
    got, e = read_ply(tmp_path / "a.ply")
    for k in v:
        np.testing.assert_array_equal(got[k], v[k])
    np.testing.assert_array_equal(e, edges)
    import open3d as o3d
    pc = o3d.io.read_point_cloud(str(tmp_path / "a.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), np.stack([v["x"], v["y"], v["z"]], 1))
