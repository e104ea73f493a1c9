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
    #: how the volume was read (DICOM: the series chosen, its slices and checks); not carried by with_data
    info: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)

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
        raise InputError(f"cannot read volume {path}: {_reason(exc)}") from exc
    data = _squeeze_3d(np.asarray(data), path)
    if min(data.shape) < 1:
        raise InputError(f"{path}: empty volume, shape {tuple(data.shape)}")
    check_affine(_mm_to_m(affine_mm), path)
    return Volume(data, _mm_to_m(affine_mm))


def check_affine(affine_m: np.ndarray, path=None) -> None:
    """A singular, non-finite or non-orthogonal (sheared) voxel-to-world affine is an :class:`InputError`."""
    where = str(path) if path is not None else "volume"
    a = np.asarray(affine_m, dtype=np.float64)
    if a.shape != (4, 4) or not np.isfinite(a).all():
        raise InputError(f"{where}: the header's affine is not a finite 4x4 matrix")
    cols = a[:3, :3]
    sp = np.linalg.norm(cols, axis=0)
    if (sp <= 1e-9).any() or abs(np.linalg.det(cols)) <= 1e-18:
        raise InputError(f"{where}: singular affine (voxel spacing {np.round(sp / MM, 4).tolist()} mm): "
                         "the header gives no valid voxel geometry")
    unit = cols / sp
    shear = float(np.abs(unit.T @ unit - np.eye(3)).max())
    if shear > 1e-3:
        ang = float(np.degrees(np.arcsin(min(1.0, shear))))
        raise InputError(f"{where}: non-orthogonal affine (voxel axes sheared by {ang:.2f} deg): "
                         "resample it to an orthogonal grid first")


def _reason(exc: BaseException) -> str:
    """One line of a library's exception: ITK's 'sitk::ERROR: ...' line, not its source location."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in lines:
        if "ERROR:" in ln:
            return ln.split("ERROR:", 1)[1].strip()
    return f"{type(exc).__name__}: {lines[0]}" if lines else type(exc).__name__


def _mm_to_m(affine_mm: np.ndarray) -> np.ndarray:
    a = np.array(affine_mm, dtype=np.float64)
    a[:3, :] *= MM
    return a


def _m_to_mm(affine_m: np.ndarray) -> np.ndarray:
    a = np.array(affine_m, dtype=np.float64)
    a[:3, :] /= MM
    return a


def _sitk():
    """SimpleITK with its warnings off: they go to stderr beside the one error line (the checks here report)."""
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    return sitk


def _itk_to_array_affine(img) -> tuple[np.ndarray, np.ndarray]:
    sitk = _sitk()

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
    sitk = _sitk()

    return _itk_to_array_affine(sitk.ReadImage(str(path)))


#: DICOM tags read per slice: ImagePositionPatient, ImageOrientationPatient, SeriesInstanceUID
_TAG_POS, _TAG_ORI, _TAG_SERIES = "0020|0032", "0020|0037", "0020|000e"


def _dicom_floats(reader, tag: str, f: str, n: int) -> np.ndarray:
    if not reader.HasMetaDataKey(tag):
        raise InputError(f"{f}: DICOM slice lacks tag ({tag}) needed to place it in space")
    try:
        v = np.array([float(x) for x in reader.GetMetaData(tag).strip().split("\\")], dtype=np.float64)
    except ValueError:
        raise InputError(f"{f}: unreadable DICOM tag ({tag}): {reader.GetMetaData(tag)!r}") from None
    if v.size != n or not np.isfinite(v).all():
        raise InputError(f"{f}: DICOM tag ({tag}) has {v.size} values, expected {n} finite")
    return v


def check_dicom_slices(files: list[str], folder: Path) -> dict:
    """Check one series' slices as a radiology reader does; return what was found (for ``ct_metadata.json``).

    Errors: slices with different orientations or from different series, two slices at one position
    (a series stored twice, or two acquisitions), a gap larger than 1.5x the median slice spacing
    (missing slices) and spacing that varies by more than 10 % (a variable-pitch series).
    """
    sitk = _sitk()

    pos, ori, uids = [], [], set()
    for f in files:
        r = sitk.ImageFileReader()
        r.SetFileName(f)
        try:
            r.ReadImageInformation()
        except Exception as exc:
            raise InputError(f"cannot read DICOM slice {f}: {_reason(exc)}") from exc
        pos.append(_dicom_floats(r, _TAG_POS, f, 3))
        ori.append(_dicom_floats(r, _TAG_ORI, f, 6))
        if r.HasMetaDataKey(_TAG_SERIES):
            uids.add(r.GetMetaData(_TAG_SERIES).strip())
    if len(uids) > 1:
        raise InputError(f"{folder}: the chosen slices come from {len(uids)} series ({', '.join(sorted(uids))}): "
                         "mixed series")
    ori_a = np.array(ori)
    if np.abs(ori_a - ori_a[0]).max() > 1e-3:
        n_other = int((np.abs(ori_a - ori_a[0]).max(axis=1) > 1e-3).sum())
        raise InputError(f"{folder}: {n_other} of {len(files)} slices have another orientation than the first: "
                         "mixed orientations (a localiser or a reformat in the series)")
    normal = np.cross(ori_a[0, :3], ori_a[0, 3:])
    z = np.sort(np.array(pos) @ normal)
    d = np.diff(z)
    med = float(np.median(d))
    if med <= 1e-6:
        raise InputError(f"{folder}: most slices share one position: the series is stored more than once")
    dup = int((d < 0.01 * med).sum())
    if dup:
        raise InputError(f"{folder}: {dup} duplicate slice position(s) among {len(files)} slices (median spacing "
                         f"{med:.3f} mm): a series stored twice or two acquisitions in one series")
    gaps = np.nonzero(d > 1.5 * med)[0]
    if gaps.size:
        g = int(gaps[0])
        missing = int(sum(round(d[i] / med) - 1 for i in gaps))
        raise InputError(f"{folder}: {missing} missing slice(s): a gap of {d[g]:.3f} mm after position "
                         f"{z[g]:.3f} mm (median spacing {med:.3f} mm)")
    if (np.abs(d - med) > 0.1 * med).any():
        raise InputError(f"{folder}: slice spacing varies from {d.min():.3f} to {d.max():.3f} mm: resample the "
                         "series to a uniform spacing first")
    return {"slices": len(files), "slice_spacing_mm": round(med, 6),
            "series_instance_uid": next(iter(uids)) if uids else None,
            "orientation": [round(float(x), 6) for x in ori_a[0]],
            "checks": "one series, one orientation, no duplicate positions, no gaps > 1.5x median spacing"}


def _read_dicom_dir(path: Path) -> Volume:
    sitk = _sitk()

    reader = sitk.ImageSeriesReader()
    series = reader.GetGDCMSeriesIDs(str(path))
    if not series:
        raise InputError(f"{path}: folder holds no DICOM series")
    # the series with the most slices is the volume; others are usually scouts
    found = {s: list(reader.GetGDCMSeriesFileNames(str(path), s)) for s in series}
    chosen = max(sorted(found), key=lambda s: len(found[s]))
    files = found[chosen]
    if len(files) < 2:
        raise InputError(f"{path}: DICOM series has {len(files)} slice(s); a 3-D volume needs at least 2")
    info = check_dicom_slices(files, path)
    info.update({"series_chosen": chosen, "series_found": {s: len(f) for s, f in sorted(found.items())},
                 "rule": "the series with the most slices"})
    reader.SetFileNames(files)
    try:
        img = reader.Execute()
    except Exception as exc:
        raise InputError(f"cannot read DICOM series in {path}: {_reason(exc)}") from exc
    data, affine_mm = _itk_to_array_affine(img)
    check_affine(_mm_to_m(affine_mm), path)
    return Volume(data, _mm_to_m(affine_mm), info={"dicom": info})


def write_nifti(path: str | os.PathLike, volume: Volume, description: str = "",
                scale_values_to_mm: bool = False) -> None:
    """Write ``volume`` as NIfTI-1 (affine in mm, RAS+ scanner frame), atomically.

    ``scale_values_to_mm`` multiplies the voxel values by 1000 (metres -> mm),
    used for distance volumes such as the SDF.  Output bytes depend only on
    the inputs (gzip timestamp fixed), so the same config gives the same file.
    """
    import gzip

    import nibabel as nib

    check_affine(volume.affine, path)
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
