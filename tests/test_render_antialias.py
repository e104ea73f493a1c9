"""The ray caster's pixel filter at silhouettes (render/antialias.py, ``RaycastConfig.edge_samples``)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from room_pipeline.render.antialias import blackman_harris, filter_offsets, filter_quantiles, silhouette_pixels
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
from room_pipeline.render.scene import Film

from .test_raycast import look
from .test_realism import default_indirect, fold_in_front_of_the_led, straight_graph, textured_scene

MM = 1e-3


def test_filter_quantiles_are_cycles_blackman_harris():
    x = np.linspace(-0.75, 0.75, 20001)
    w = blackman_harris(x)
    sd = np.sqrt(np.sum(w * x * x) / np.sum(w))
    q = filter_quantiles(64)
    assert np.allclose(q, -q[::-1]) and np.all(np.abs(q) < 0.75)
    assert abs(np.std(q) - sd) < 0.01 and 0.18 < sd < 0.23          # the filter is narrow: sd ~0.2 px
    assert blackman_harris(np.array([0.75, -0.8])).max() == 0.0
    assert filter_offsets(3).shape == (9, 2) and np.allclose(filter_offsets(3).mean(0), 0)
    with pytest.raises(ValueError):
        filter_quantiles(0)
    with pytest.raises(ValueError):
        RaycastConfig(edge_samples=-1)


def test_silhouette_pixels():
    d = np.full((6, 6), 0.01, np.float32)
    d[:, 3:] = 0.02                       # a depth step between columns 2 and 3
    hit = np.ones((6, 6), bool)
    m = silhouette_pixels(d, hit, 0.15)
    assert m[:, 2:4].all() and not m[:, :2].any() and not m[:, 4:].any()
    hit[0, 0] = False
    assert silhouette_pixels(np.where(hit, 0.01, 0).astype(np.float32), hit, 0.15)[:2, :2].all()


def filtered_reference(sc, cfg, s: int = 9) -> np.ndarray:
    """The frame integrated with the pixel filter: s x s sub-pixel rays (a whole image at s x the resolution),
    weighted with Blackman-Harris 1.5 px."""
    import cv2

    cam = sc.camera
    hi = dataclasses.replace(sc, camera=dataclasses.replace(
        cam, width=cam.width * s, height=cam.height * s, fx=cam.fx * s, fy=cam.fy * s,
        cx=(cam.cx + 0.5) * s - 0.5, cy=(cam.cy + 0.5) * s - 0.5))
    img = RaycastRenderer(hi, cfg).render(0, {"rgb"})["rgb_linear"]
    r = int(np.floor(0.75 * s))
    taps = blackman_harris(np.arange(-r, r + 1) / s)
    taps = (taps / taps.sum()).astype(np.float32)
    out = cv2.sepFilter2D(img, -1, taps, taps, borderType=cv2.BORDER_REFLECT)
    return out[(s - 1) // 2::s, (s - 1) // 2::s]


def test_edge_samples_approach_the_filtered_pixel_at_silhouettes():
    """A fold's edge in front of the far wall: the centre ray's error against the filter-integrated pixel
    drops at the silhouette pixels; everything else (and every geometric modality) is unchanged."""
    cam = CameraIntrinsics.from_fov(40, 40, 85.0)
    sc = textured_scene(fold_in_front_of_the_led(), [look([0.5 * MM, -3 * MM, 4 * MM], [0.05, 0.1, 1.0])],
                        straight_graph(), camera=cam, film=Film(exposure_ev=0.0))
    base = RaycastConfig(indirect=default_indirect(), shading_stride=1)
    ref = filtered_reference(sc, base)
    a = RaycastRenderer(sc, base).render(0, {"rgb", "depth", "normals"})
    b = RaycastRenderer(sc, dataclasses.replace(base, edge_samples=3)).render(0, {"rgb", "depth", "normals"})
    sil = silhouette_pixels(a["depth"], a["hit"], base.edge_depth_jump)
    assert 0.01 < sil.mean() < 0.5
    assert np.array_equal(a["rgb_linear"][~sil], b["rgb_linear"][~sil])
    assert np.array_equal(a["depth"], b["depth"]) and np.array_equal(a["normals"], b["normals"])
    assert np.all(np.isfinite(b["rgb_linear"]))
    e_a = np.mean((a["rgb_linear"][sil] - ref[sil]) ** 2)
    e_b = np.mean((b["rgb_linear"][sil] - ref[sil]) ** 2)
    print("silhouettes", sil.mean(), "mse centre ray", e_a, "edge samples", e_b)
    assert e_b < 0.5 * e_a, (e_a, e_b)
    # deterministic
    c = RaycastRenderer(sc, dataclasses.replace(base, edge_samples=3)).render(0, {"rgb"})
    assert np.array_equal(b["rgb"], c["rgb"])
