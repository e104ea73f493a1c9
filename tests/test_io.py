"""Volume and mesh I/O: formats, frames, atomic writes, one-line errors."""
from __future__ import annotations

import errno
import gzip
import os
import subprocess
import sys

import numpy as np
import pytest

from room_pipeline.errors import InputError
from room_pipeline.io.atomic import FILE_MODE, atomic_path, write_bytes, write_json, write_with
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


def _current_umask() -> int:
    old = os.umask(0o022)
    os.umask(old)
    return old


def test_atomic_files_get_the_umask_mode_not_mkstemps(tmp_path):
    """mkstemp makes 0600 files; an atomic write gives what open(path, "w") would: 0666 less the umask."""
    assert FILE_MODE == 0o666 & ~_current_umask()
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    write_json(tmp_path / "a.json", {"a": 1})
    write_bytes(tmp_path / "b.bin", b"\x00")
    write_with(tmp_path / "c.npy", lambda tmp: np.save(tmp, np.arange(3)))        # a library writing the path
    for name in ("a.json", "b.bin", "c.npy"):
        assert (tmp_path / name).stat().st_mode & 0o777 == plain.stat().st_mode & 0o777 == FILE_MODE
    with atomic_path(tmp_path / "d.txt") as tmp:                                 # the temporary file already has it
        assert tmp.stat().st_mode & 0o777 == FILE_MODE
        tmp.write_text("d")


def test_atomic_mode_follows_the_process_umask(tmp_path):
    code = ("import os, sys; os.umask(0o027); from room_pipeline.io.atomic import write_text; "
            "write_text(sys.argv[1], 'x'); print(oct(os.stat(sys.argv[1]).st_mode & 0o777))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "f.txt")], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "0o640"


def test_atomic_write_errors_are_one_line_input_errors(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"previous")

    def full(tmp):                                  # what a full disk looks like to a writer, half-way through
        tmp.write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(InputError) as ei:
        write_with(target, full)
    assert str(ei.value) == f"cannot write {target}: No space left on device"
    assert isinstance(ei.value.__cause__, OSError)
    assert target.read_bytes() == b"previous" and sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]

    (tmp_path / "adir").mkdir()                      # the rename fails: the target is a folder
    with pytest.raises(InputError, match=r"^cannot write .*adir: Is a directory$"):
        write_bytes(tmp_path / "adir", b"x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "out.bin"]

    with pytest.raises(InputError, match=r"^cannot write .*out\.bin/x\.json: "):   # the parent is a file
        write_json(target / "x.json", {})
    assert target.read_bytes() == b"previous"

    def bad_value(tmp):
        tmp.write_bytes(b"partial")
        raise ValueError("not an OSError")

    with pytest.raises(ValueError, match="^not an OSError$"):                   # other errors pass unchanged
        write_with(tmp_path / "v.bin", bad_value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "out.bin"]


@pytest.mark.skipif(os.geteuid() == 0, reason="running as root: permissions are not enforced for root")
def test_atomic_write_into_an_unwritable_folder(tmp_path):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        with pytest.raises(InputError, match=r"^cannot write .*ro/f\.json: Permission denied$"):
            write_json(d / "f.json", {})
    finally:
        d.chmod(0o700)


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
