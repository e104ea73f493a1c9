"""3-D volumes: reading CT / mask files into :class:`Volume` and writing NIfTI.

Formats read: NIfTI (``.nii``, ``.nii.gz``) through nibabel; NRRD / MetaImage
(``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``) and DICOM series folders through
SimpleITK.  Everything is converted to the world frame of
:mod:`room_pipeline.conventions` (RAS+, metres).
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ..conventions import MM
from ..errors import InputError
from .atomic import atomic_path

NIFTI_SUFFIXES = (".nii", ".nii.gz")
ITK_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd")
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclasses.dataclass
class Volume:
    """A voxel grid in world space.

    Attributes:
        data: array indexed (i, j, k).
        affine: 4x4, homogeneous voxel index -> world RAS+ position in **metres**.
    """

    data: np.ndarray
    affine: np.ndarray

    def __post_init__(self) -> None:
        self.affine = np.asarray(self.affine, dtype=np.float64)
        if self.data.ndim != 3:
            raise InputError(f"expected a 3-D volume, got shape {self.data.shape}")
        if self.affine.shape != (4, 4):
            raise InputError(f"affine must be 4x4, got {self.affine.shape}")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along i, j, k in metres."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def with_data(self, data: np.ndarray) -> "Volume":
        """Same grid, new voxel values."""
        return Volume(data, self.affine.copy())

    def index_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """(N, 3) voxel indices (float allowed) -> (N, 3) world positions in metres."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_index(self, xyz: np.ndarray) -> np.ndarray:
        """(N, 3) world positions in metres -> (N, 3) continuous voxel indices."""
        inv = np.linalg.inv(self.affine)
        xyz = np.asarray(xyz, dtype=np.float64)
        return xyz @ inv[:3, :3].T + inv[:3, 3]

    def superior_axis(self) -> tuple[int, int]:
        """(voxel axis, sign) whose direction is closest to world +z (superior)."""
        cols = self.affine[:3, :3] / self.spacing
        axis = int(np.argmax(np.abs(cols[2])))
        return axis, int(np.sign(cols[2, axis]) or 1)


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for s in NIFTI_SUFFIXES + ITK_SUFFIXES:
        if name.endswith(s):
            return s
    return path.suffix.lower()


def _squeeze_3d(data: np.ndarray, path: Path) -> np.ndarray:
    if data.ndim > 3:
        extra = data.shape[3:]
        if all(n == 1 for n in extra):
            data = data.reshape(data.shape[:3])
    if data.ndim != 3:
        raise InputError(f"{path}: expected a 3-D volume, got shape {tuple(data.shape)}")
    return data


def read_volume(path: str | os.PathLike) -> Volume:
    """Read a NIfTI / NRRD / MetaImage file or a DICOM series folder.

    Raises :class:`InputError` with a one-line reason for a missing path, an
    unreadable file or a volume that is not 3-D.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"input not found: {path}")
    if path.is_dir():
        return _read_dicom_dir(path)
    suffix = _suffix(path)
    try:
        if suffix in NIFTI_SUFFIXES:
            import nibabel as nib

            img = nib.load(str(path))
            data = np.asanyarray(img.dataobj)
            affine_mm = np.asarray(img.affine, dtype=np.float64)
        elif suffix in ITK_SUFFIXES:
            data, affine_mm = _read_itk(path)
        else:
            raise InputError(f"{path}: unsupported volume format '{suffix}' "
                             f"(use .nii/.nii.gz, .nrrd/.mha or a DICOM folder)")
    except InputError:
        raise
    except Exception as exc:  # nibabel/ITK raise many types; report one line
        raise InputError(f"cannot read volume {path}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from exc
    data = _squeeze_3d(np.asarray(data), path)
    if min(data.shape) < 1:
        raise InputError(f"{path}: empty volume, shape {tuple(data.shape)}")
    return Volume(data, _mm_to_m(affine_mm))


def _mm_to_m(affine_mm: np.ndarray) -> np.ndarray:
    a = np.array(affine_mm, dtype=np.float64)
    a[:3, :] *= MM
    return a


def _m_to_mm(affine_m: np.ndarray) -> np.ndarray:
    a = np.array(affine_m, dtype=np.float64)
    a[:3, :] /= MM
    return a


def _itk_to_array_affine(img) -> tuple[np.ndarray, np.ndarray]:
    import SimpleITK as sitk

    if img.GetDimension() != 3:
        raise InputError(f"expected a 3-D image, got {img.GetDimension()}-D")
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(f"expected a scalar image, got {img.GetNumberOfComponentsPerPixel()} components per voxel")
    arr = sitk.GetArrayFromImage(img)  # (k, j, i)
    data = np.ascontiguousarray(np.transpose(arr, (2, 1, 0)))
    direction = np.array(img.GetDirection(), dtype=np.float64).reshape(3, 3)
    spacing = np.array(img.GetSpacing(), dtype=np.float64)
    origin = np.array(img.GetOrigin(), dtype=np.float64)
    lps = np.eye(4)
    lps[:3, :3] = direction * spacing[None, :]
    lps[:3, 3] = origin
    return data, _LPS_TO_RAS @ lps


def _read_itk(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import SimpleITK as sitk

    return _itk_to_array_affine(sitk.ReadImage(str(path)))


def _read_dicom_dir(path: Path) -> Volume:
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    series = reader.GetGDCMSeriesIDs(str(path))
    if not series:
        raise InputError(f"{path}: folder holds no DICOM series")
    # the series with the most slices is the volume; others are usually scouts
    files = max((reader.GetGDCMSeriesFileNames(str(path), s) for s in series), key=len)
    if len(files) < 2:
        raise InputError(f"{path}: DICOM series has {len(files)} slice(s); a 3-D volume needs at least 2")
    reader.SetFileNames(files)
    try:
        img = reader.Execute()
    except Exception as exc:
        raise InputError(f"cannot read DICOM series in {path}: {str(exc).splitlines()[0]}") from exc
    data, affine_mm = _itk_to_array_affine(img)
    return Volume(data, _mm_to_m(affine_mm))


def write_nifti(path: str | os.PathLike, volume: Volume, description: str = "",
                scale_values_to_mm: bool = False) -> None:
    """Write ``volume`` as NIfTI-1 (affine in mm, RAS+ scanner frame), atomically.

    ``scale_values_to_mm`` multiplies the voxel values by 1000 (metres -> mm),
    used for distance volumes such as the SDF.  Output bytes depend only on
    the inputs (gzip timestamp fixed), so the same config gives the same file.
    """
    import gzip

    import nibabel as nib

    data = volume.data
    if scale_values_to_mm:  # slab by slab: same values as one float64 pass, a quarter of the memory
        src = np.asarray(data)
        data = np.empty(src.shape, dtype=np.float32)
        for i in range(0, src.shape[0], 32):
            data[i:i + 32] = (src[i:i + 32].astype(np.float64) / MM).astype(np.float32)
    img = nib.Nifti1Image(data, _m_to_mm(volume.affine))
    img.set_qform(img.affine, code=1)
    img.set_sform(img.affine, code=1)
    img.header.set_xyzt_units(xyz="mm", t="sec")
    if description:
        img.header["descrip"] = description[:79].encode("ascii", "replace")
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            if path.name.endswith(".gz"):
                with gzip.GzipFile(fileobj=fh, mode="wb", mtime=0, filename="", compresslevel=6) as gz:
                    _write_nifti_stream(img, gz)
            else:
                _write_nifti_stream(img, fh)


def _write_nifti_stream(img, fh) -> None:
    """The bytes of ``img.to_bytes()`` (header, extension flag, Fortran-order data), written slab by slab."""
    arr = np.asanyarray(img.dataobj)
    hdr = img.header
    hdr.set_data_dtype(arr.dtype)
    hdr.set_data_shape(arr.shape)
    if not (arr.ndim == 3 and np.isnan(hdr["scl_slope"]) and arr.dtype.isnative) or img.extra or \
            hdr.extensions or int(hdr.get_data_offset()) not in (0, 352):
        fh.write(img.to_bytes())  # anything unusual: nibabel's own writer
        return
    hdr.set_data_offset(352)
    hdr["scl_slope"], hdr["scl_inter"] = 1.0, 0.0  # what nibabel's writer stores for unscaled data
    fh.write(hdr.binaryblock)
    fh.write(b"\x00" * 4)  # no extensions
    for k in range(arr.shape[2]):  # Fortran order: the last axis is the slowest
        fh.write(np.asfortranarray(arr[:, :, k]).tobytes(order="F"))


def read_nifti_sdf(path: str | os.PathLike) -> Volume:
    """Read an SDF NIfTI written with ``scale_values_to_mm=True``; values back in metres."""
    vol = read_volume(path)
    src = np.asarray(vol.data)
    out = np.empty(src.shape, dtype=np.float32)
    for i in range(0, src.shape[0], 32):  # slab by slab: same values as one float64 pass, less memory
        out[i:i + 32] = (src[i:i + 32].astype(np.float64) * MM).astype(np.float32)
    return vol.with_data(out)
