"""Units, frames and sign conventions used by every room-pipeline output.

This module is the single place where they are written down; every output's
metadata carries :func:`metadata_block` so that a file explains itself.

Units
    SI everywhere in memory and in the project's own file formats (JSON, OBJ,
    PLY, NPZ, EXR): metres, radians, seconds.  The one exception is NIfTI
    volumes, whose standard spatial unit is the millimetre: their affines are
    in mm and the header's ``xyzt_units`` says so (what every viewer expects,
    so CT, mask and SDF overlay in 3D Slicer or ITK-SNAP).  The SDF volume
    ``sdf.nii.gz`` therefore stores millimetres; in memory it is metres.

World frame
    The CT's physical (scanner) frame in the **RAS+** convention of NIfTI and
    nibabel: +x points to the patient's Right, +y Anterior, +z Superior
    (towards the head).  DICOM/ITK images (LPS+) are converted on reading by
    negating x and y.

Voxel grids
    A :class:`room_pipeline.io.volume.Volume` holds an array indexed (i, j, k)
    and a 4x4 affine mapping homogeneous voxel indices to world RAS+ metres;
    voxel *centres* sit at integer indices.

Signed distance
    Negative inside the airway lumen (air), positive in wall and tissue, zero
    on the lumen surface; its gradient is the outward normal of the lumen
    (pointing from air into tissue).  The local lumen radius at a centreline
    point is therefore ``-sdf``.

Meshes
    ``lung_model.obj``: the closed lumen surface in world RAS+ metres, faces
    wound counter-clockwise seen from outside the lumen, so face normals point
    from air into tissue (the standard orientation of a closed solid).
    ``collision_model.obj``: the same surface decimated for the scope physics,
    same units and winding, within ``mesh.collision_max_error_mm`` of it.

Cameras (later stages)
    OpenCV camera frame (x right, y down, z forward); poses are 4x4
    camera-to-world transforms; depth is planar z-depth in metres; optical
    flow is forward (t -> t+1) in pixels.  Images and lens distortion: every
    rendered image (RGB and the geometric modalities: depth, normals, flow,
    segmentation, point-cloud pixels) is in the *distorted* image of
    ``calibration/camera_params.json`` (OpenCV k1, k2, p1, p2, k3; all zero =
    ideal pinhole): pixel (u, v) sees the surface along the undistorted
    direction of that pixel centre, and flow targets are distorted pixels.
"""
from __future__ import annotations

WORLD_FRAME = "RAS+"
LENGTH_UNIT = "m"
NIFTI_LENGTH_UNIT = "mm"
SDF_SIGN = "negative inside the airway lumen, positive outside; gradient = outward lumen normal"
MESH_ORIENTATION = "closed lumen surface, counter-clockwise seen from outside, normals point from air into tissue"
CAMERA_FRAME = "OpenCV: x right, y down, z forward"
POSE_CONVENTION = "4x4 camera-to-world"
IMAGE_CONVENTION = ("every image (rgb, depth, normals, flow, segmentation) is in the distorted image of "
                    "camera_params.json (OpenCV k1, k2, p1, p2, k3; zero = pinhole)")

#: metres per millimetre
MM = 1e-3


def metadata_block() -> dict:
    """The conventions as a JSON-serialisable dict, embedded in every output's metadata."""
    return {
        "units": {"length": LENGTH_UNIT, "angle": "rad", "time": "s",
                  "nifti_length": NIFTI_LENGTH_UNIT, "ct_intensity": "HU"},
        "world_frame": WORLD_FRAME,
        "world_frame_axes": "+x patient Right, +y Anterior, +z Superior",
        "affine": "4x4, homogeneous voxel index (i, j, k, 1) -> world; voxel centres at integer indices",
        "sdf_sign": SDF_SIGN,
        "mesh_orientation": MESH_ORIENTATION,
        "camera_frame": CAMERA_FRAME,
        "pose": POSE_CONVENTION,
        "image": IMAGE_CONVENTION,
    }
