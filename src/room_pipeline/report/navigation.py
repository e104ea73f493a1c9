"""The ``navigation`` section: the paper's navigation demonstration (``room navigate demo``) in 2-D and 3-D.

Shown only for a dataset that holds demo output: a ``navigation_demo.json`` (with its ``frame_NNNN_path.png`` /
``.ply``) at most three folders below the dataset root, outside the rendered sequence folders (the README's
``--out <output_dir>/<patient>/navigation/<sequence>``).  Per planned frame: the RGB with the projected path
(as the demo drew it) and a 3-D view in the world frame (RAS+, m) of the back-projected point cloud (the PLY),
the path, the scope's collision spheres along it (radius ``planner.scope_radius_mm``; red from the first one
that meets the TRUE lumen, else green) and the true lumen mesh (the patient's ``anatomy/lung_model.obj``)
within 6 mm of them.  Drawn as :mod:`.draw3d` draws: pyvista off-screen, else matplotlib 3-D (and says so).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..catalog import SequencePaths
from ..errors import InputError
from .common import esc, img_tag, jpeg_uri, na, show_path
from .options import ReportOptions

DEMO_JSON = "navigation_demo.json"
#: the section's id and heading (inserted after the view3d section when a demo output exists)
NAVIGATION_SECTION = ("navigation", "Navigation demonstration (path on the image and in 3-D)")
_C = {"cloud": (0.55, 0.45, 0.42), "path": (0.16, 0.35, 0.85), "free": (0.15, 0.75, 0.25),
      "hit": (0.90, 0.10, 0.10), "lumen": (0.86, 0.62, 0.56)}


def find_demos(root: Path) -> list[Path]:
    """``navigation_demo.json`` files up to three folders below ``root`` (sorted), rendered sequences skipped."""
    out, level = [], [Path(root)]
    for _ in range(4):
        nxt = []
        for d in level:
            if (d / DEMO_JSON).is_file():
                out.append(d / DEMO_JSON)
            nxt += [c for c in sorted(d.iterdir()) if c.is_dir() and not c.name.startswith(".")
                    and not SequencePaths(c).render_json.exists()]
        level = nxt
    return sorted(out)


def read_ply_points(path: Path) -> np.ndarray:
    """(N, 3) float64 vertices of the demo's binary PLY (x, y, z float32 + r, g, b uint8 per vertex)."""
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    n = [int(ln.split()[2]) for ln in data[:end].decode("ascii", "replace").splitlines()
         if ln.startswith("element vertex")]
    rec = np.frombuffer(data, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")],
                        count=n[0] if n else 0, offset=end + len(b"end_header\n"))
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)


def _mesh_near(mesh, pts: np.ndarray, pad: float = 0.006):
    lo, hi = pts.min(0) - pad, pts.max(0) + pad
    inside = np.all((mesh.vertices >= lo) & (mesh.vertices <= hi), axis=1)
    faces = mesh.faces[inside[mesh.faces].all(axis=1)]
    return mesh.vertices, faces


def _view(cloud: np.ndarray, path: np.ndarray, tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(focal point, camera position, up): behind and beside the path's start, looking along it."""
    t = tangent / (np.linalg.norm(tangent) or 1.0)
    side = np.cross(t, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0.0, 0.0])
    allp = np.vstack([cloud, path])
    c = allp.mean(0)
    ext = float(np.linalg.norm(np.ptp(allp, axis=0))) or 0.05
    return c, c - 0.9 * ext * t + 0.9 * ext * side, np.cross(side, t)


def render_demo_3d(cloud, path, tangent, radius, first_hit, mesh_vf, size, use_pyvista) -> tuple[np.ndarray, str]:
    """(H, W, 3) uint8 image of one demo frame's 3-D scene and how it was drawn."""
    c, eye, up = _view(cloud, path, tangent)
    hit = np.arange(len(path)) >= (first_hit if first_hit is not None else len(path))
    if use_pyvista:
        try:
            return _pyvista(cloud, path, radius, hit, mesh_vf, size, c, eye, up), "pyvista (VTK, off-screen)"
        except Exception as exc:  # any VTK/OpenGL failure: fall back, and say so
            why = f"{exc.__class__.__name__}: {exc}".splitlines()[0][:200]
    else:
        why = "disabled (use_pyvista=False)"
    return _matplotlib(cloud, path, hit, mesh_vf, size, c, eye), f"matplotlib 3-D fallback (pyvista: {why})"


def _pyvista(cloud, path, radius, hit, mesh_vf, size, c, eye, up) -> np.ndarray:
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        pl.set_background("white")
        if mesh_vf is not None and len(mesh_vf[1]):
            V, F = mesh_vf
            pl.add_mesh(pv.PolyData(V, np.hstack([np.full((len(F), 1), 3), F]).ravel()).clean(),
                        color=_C["lumen"], opacity=0.25)
        pl.add_mesh(pv.PolyData(cloud), color=_C["cloud"], point_size=3)
        pl.add_mesh(pv.PolyData(path, lines=np.concatenate([[len(path)], np.arange(len(path))])).tube(
            radius=0.15 * radius), color=_C["path"])
        for k, p in enumerate(path[::2]):
            pl.add_mesh(pv.Sphere(radius=radius, center=tuple(p), theta_resolution=12, phi_resolution=8),
                        color=_C["hit" if hit[2 * k] else "free"], opacity=0.3)
        pl.camera.focal_point, pl.camera.position, pl.camera.up = tuple(c), tuple(eye), tuple(up)
        img = pl.screenshot(return_img=True)
    finally:
        pl.close()
    return np.ascontiguousarray(np.asarray(img)[..., :3], dtype=np.uint8)


def _matplotlib(cloud, path, hit, mesh_vf, size, c, eye) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    if mesh_vf is not None and len(mesh_vf[1]):
        V = mesh_vf[0][np.unique(mesh_vf[1])]
        ax.scatter(*V.T, s=0.4, c=[_C["lumen"]], alpha=0.3, linewidths=0)
    ax.scatter(*cloud[:: max(1, len(cloud) // 4000)].T, s=0.8, c=[_C["cloud"]], linewidths=0)
    ax.plot(*path.T, color=_C["path"], lw=2)
    for flag, key in ((False, "free"), (True, "hit")):
        P = path[hit == flag]
        if len(P):
            ax.scatter(*P.T, s=30, c=[_C[key]], alpha=0.35)
    d = eye - c
    ax.view_init(elev=float(np.degrees(np.arcsin(d[2] / np.linalg.norm(d)))), azim=float(np.degrees(np.arctan2(d[1], d[0]))))
    half = max(float(np.ptp(np.vstack([cloud, path]), axis=0).max()) / 2, 1e-3)
    for setl, ci in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), c):
        setl(ci - half, ci + half)
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _patient_mesh(demo: Path, root: Path, doc: dict):
    """The true lumen mesh: of the patient folder the demo output lies in, else of the sequence it names."""
    from ..io.mesh import read_obj
    from ..paths import PatientPaths

    rel = demo.relative_to(root).parts
    cands = [PatientPaths(root, rel[0]).mesh] if len(rel) > 1 else []
    seq = Path(str(doc.get("sequence", "")))
    cands.append(PatientPaths(seq.parent.parent, seq.parent.name).mesh)
    for m in cands:
        if m.is_file():
            return read_obj(m), m
    return None, cands[0]


def section_navigation(opts: ReportOptions) -> str | None:
    """The section's HTML, or None when the dataset holds no demo output (then the page has no such section)."""
    root = Path(opts.output_dir)
    demos = find_demos(root)
    if not demos:
        return None
    out = []
    for demo in demos:
        folder = demo.parent
        out.append(f"<h3>{esc(show_path(folder, opts.base))}</h3>")
        try:
            doc = json.loads(demo.read_text(encoding="utf-8"))
            frames = list(doc["frames"])
            radius = float(doc["planner"]["scope_radius_mm"]) * 1e-3
        except (OSError, ValueError, KeyError, TypeError) as exc:
            out.append(na(f"{demo.name} unreadable ({exc.__class__.__name__}: {exc})"))
            continue
        mesh, mesh_path = _patient_mesh(demo, root, doc)
        for f in frames:
            name = f"frame_{int(f.get('frame', -1)):04d}"
            png, ply = folder / f"{name}_path.png", folder / f"{name}_path.ply"
            if f.get("path_world_m") is None or not png.is_file() or not ply.is_file():
                out.append(na(f"{name}: no path ({f.get('reason', 'PNG/PLY missing')})"))
                continue
            import cv2

            rgb = cv2.imread(str(png), cv2.IMREAD_COLOR)[..., ::-1]
            path = np.asarray(f["path_world_m"], dtype=np.float64)
            pts = read_ply_points(ply)
            cloud = pts[: max(0, len(pts) - len(path))]
            t = f.get("true_lumen") or {}
            mesh_vf = _mesh_near(mesh, np.vstack([cloud, path])) if mesh is not None else None
            img3, how = render_demo_3d(cloud if len(cloud) else path, path, np.asarray(f["tangents_world"][0]), radius,
                                       t.get("first_collision_index"), mesh_vf, opts.view_size, opts.use_pyvista)
            scale = f", median scale {f['median_scale']:.3g}" if f.get("median_scale") else ""
            cap = (f"{name} ({esc(f.get('depth_source', '?'))} depth{scale}): path {1e3 * f['length_m']:.1f} mm, ending "
                   f"{1e3 * f['end_to_goal_m']:.1f} mm short of the goal at {1e3 * f['goal_depth_m']:.1f} mm depth; "
                   f"free against the cloud: {f['collision_free_against_cloud']}; collides with the true lumen: "
                   f"{t.get('collides_with_true_lumen')} (min sphere clearance "
                   f"{t.get('min_sphere_clearance_mm', float('nan')):.2f} mm)")
            w = rgb.shape[1]
            out.append('<div class="views">'
                       f'<figure>{img_tag(jpeg_uri(rgb), f"{name} path on the image", w, rgb.shape[0])}'
                       f"<figcaption>{cap}. Green: clear of the true lumen, red: collides; cyan: goal.</figcaption></figure>"
                       f'<figure>{img_tag(jpeg_uri(img3), f"{name} 3-D", img3.shape[1], img3.shape[0])}'
                       f"<figcaption>3-D, world frame: point cloud (brown), path (blue), collision spheres "
                       f"(radius {1e3 * radius:.1f} mm; green clear, red from the first touching the true lumen), "
                       f"true lumen mesh within 6 mm (pink"
                       f"{'' if mesh is not None else '; not drawn: no ' + esc(show_path(mesh_path, opts.base))}"
                       f"); drawn by {esc(how)}.</figcaption></figure></div>")
    return "\n".join(out)
