"""Drawing a :class:`~room_pipeline.report.scene.Scene3D` off-screen (pyvista, or matplotlib 3-D) and the ``view3d`` section."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError
from .common import esc, img_tag, na, show_path, jpeg_uri
from .discovery import find_sequence_dirs
from .options import COLOURS, ReportOptions
from .scene import Scene3D, sequence_scene

def _bounds(points: Sequence[np.ndarray], pad: float) -> tuple[float, ...]:
    P = np.vstack([np.reshape(p, (-1, 3)) for p in points])
    lo, hi = P.min(0) - pad, P.max(0) + pad
    return (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])


def _path_points(sc: Scene3D) -> list[np.ndarray]:
    pts = [p for p in (sc.planned, sc.simulated, sc.rendered) if p is not None and len(p)]
    return pts + [s for s in sc.scopes if len(s)]


def _closeup_bounds(sc: Scene3D, radius: float = 0.03, pad: float = 0.004) -> tuple[float, ...]:
    """Bounds of the drawn points within ``radius`` (m) of the distal end (the last simulated tip,
    else the last planned or rendered position), padded by ``pad``."""
    ends = [p for p in (sc.tips, sc.simulated, sc.planned, sc.rendered) if p is not None and len(p)]
    end = np.asarray(ends[0])[-1]
    P = np.vstack([np.reshape(p, (-1, 3)) for p in _path_points(sc)])
    near = P[np.linalg.norm(P - end, axis=1) <= radius]
    return _bounds([near if len(near) else end[None]], pad)


def render_pyvista(sc: Scene3D, size: tuple[int, int], closeup: bool) -> np.ndarray:
    """Off-screen pyvista screenshot (H, W, 3) uint8; anterior view (camera on +y, up +z, so the
    patient's right is on the image left, as in radiology).  Raises whatever VTK raises."""
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    # without a display VTK tries X first and logs a warning before it falls back to EGL / OSMesa
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    path = _path_points(sc)
    ext = np.ptp(np.vstack([sc.mesh_vertices] + path) if sc.mesh_vertices is not None else np.vstack(path), axis=0)
    diag = float(np.linalg.norm(ext)) or 0.1
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        pl.set_background("white")
        # translucent airway and scope: depth peeling, which needs multisampling off (SSAA instead;
        # VTK's FXAA is not supported by its EGL / OSMesa builds)
        pl.disable_anti_aliasing()
        pl.enable_depth_peeling(number_of_peels=8, occlusion_ratio=0.0)
        pl.enable_anti_aliasing("ssaa")
        if sc.mesh_vertices is not None:
            faces = np.hstack([np.full((len(sc.mesh_faces), 1), 3), sc.mesh_faces]).ravel()
            pl.add_mesh(pv.PolyData(sc.mesh_vertices, faces), color=COLOURS["airway"], opacity=0.22,
                        smooth_shading=True)
        r_line = (0.00035 if closeup else 0.003 * diag)

        def polyline(P):   # one polyline cell (not a cell per segment, whose tubes would each be capped)
            P = np.asarray(P, dtype=np.float64)
            return pv.PolyData(P, lines=np.concatenate([[len(P)], np.arange(len(P))]))

        def line(P, colour, r):
            if P is not None and len(P) >= 2:
                pl.add_mesh(polyline(P).tube(radius=r, n_sides=10), color=colour)

        line(sc.planned, COLOURS["planned"], r_line)
        line(sc.simulated, COLOURS["simulated"], r_line)
        if sc.rendered is not None and len(sc.rendered):
            pl.add_mesh(pv.PolyData(np.asarray(sc.rendered)), color=COLOURS["rendered"],
                        point_size=7 if closeup else 5, render_points_as_spheres=True)
        if closeup:   # the scope at its true diameter, translucent so the paths inside stay visible
            for s in sc.scopes:
                if len(s) >= 2:
                    pl.add_mesh(polyline(s).tube(radius=sc.scope_radius, n_sides=20),
                                color=COLOURS["scope"], opacity=0.35)
            for t in (sc.tips if sc.tips is not None else []):
                pl.add_mesh(pv.Sphere(radius=0.5 * sc.scope_radius, center=tuple(t)), color=COLOURS["tip"])
        if closeup:
            b = _closeup_bounds(sc)
        else:
            b = _bounds([sc.mesh_vertices], 0.0) if sc.mesh_vertices is not None else _bounds(path, 0.004)
        c = np.array([(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2])
        pl.camera.focal_point = tuple(c)
        pl.camera.position = tuple(c + np.array([0.0, 1.0, 0.0]))
        pl.camera.up = (0.0, 0.0, 1.0)
        pl.reset_camera(bounds=b)
        if not closeup:
            pl.camera.zoom(1.15)
        img = pl.screenshot(return_img=True)
    finally:
        pl.close()
    return np.ascontiguousarray(np.asarray(img)[..., :3], dtype=np.uint8)


def render_matplotlib(sc: Scene3D, size: tuple[int, int], closeup: bool) -> np.ndarray:
    """The matplotlib 3-D fallback (mesh as a light point cloud), same content and viewpoint."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    path = _path_points(sc)
    if sc.mesh_vertices is not None:
        V = sc.mesh_vertices
        if closeup:
            b = _closeup_bounds(sc, pad=0.008)
            V = V[(V[:, 0] >= b[0]) & (V[:, 0] <= b[1]) & (V[:, 1] >= b[2]) & (V[:, 1] <= b[3])
                  & (V[:, 2] >= b[4]) & (V[:, 2] <= b[5])]
        V = V[:: max(1, len(V) // 15000)]
        ax.scatter(V[:, 0], V[:, 1], V[:, 2], s=0.3, c=[COLOURS["airway"]], alpha=0.25, linewidths=0)
    for P, key in ((sc.planned, "planned"), (sc.simulated, "simulated")):
        if P is not None and len(P):
            ax.plot(P[:, 0], P[:, 1], P[:, 2], color=COLOURS[key], lw=1.5)
    if sc.rendered is not None and len(sc.rendered):
        R = sc.rendered
        ax.scatter(R[:, 0], R[:, 1], R[:, 2], s=8, c=[COLOURS["rendered"]])
    if closeup:
        for s in sc.scopes:
            ax.plot(s[:, 0], s[:, 1], s[:, 2], color=COLOURS["scope"], lw=4, alpha=0.6)
        if sc.tips is not None and len(sc.tips):
            ax.scatter(sc.tips[:, 0], sc.tips[:, 1], sc.tips[:, 2], s=25, c=[COLOURS["tip"]])
    if closeup:
        b = _closeup_bounds(sc)
    else:
        b = _bounds([sc.mesh_vertices], 0) if sc.mesh_vertices is not None else _bounds(path, 0.004)
    half = max(b[1] - b[0], b[3] - b[2], b[5] - b[4]) / 2
    c = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
    ax.set_xlim(c[0] - half, c[0] + half)
    ax.set_ylim(c[1] - half, c[1] + half)
    ax.set_zlim(c[2] - half, c[2] + half)
    ax.view_init(elev=0, azim=90)   # from +y (anterior), z up
    ax.set_xlabel("x (m, R)")
    ax.set_zlabel("z (m, S)")
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _legend(sc: Scene3D) -> str:
    items = [("airway", "airway lumen (semi-transparent)", sc.mesh_vertices is not None),
             ("planned", "planned trajectory", sc.planned is not None),
             ("simulated", "simulated tip path", sc.simulated is not None),
             ("rendered", "rendered cameras", sc.rendered is not None),
             ("scope", "scope backbone (tube)", bool(sc.scopes)),
             ("tip", "simulated tip at those frames", bool(sc.scopes))]
    sw = lambda c: "#%02x%02x%02x" % tuple(round(255 * x) for x in c)  # noqa: E731
    return '<p class="legend">' + " ".join(
        f'<span class="sw" style="background:{sw(COLOURS[k])}"></span>{esc(t)}' for k, t, on in items if on) + "</p>"


def section_view3d(opts: ReportOptions, patients: list[Path]) -> str:
    from ..io.mesh import read_obj
    from ..paths import PatientPaths

    out = []
    pyvista_error: str | None = None if opts.use_pyvista else "disabled (use_pyvista=False)"
    for p in patients:
        seqs = find_sequence_dirs(p)
        if not seqs:
            continue
        mesh_path = PatientPaths(p.parent, p.name).mesh
        mesh = None
        try:
            mesh = read_obj(mesh_path) if mesh_path.is_file() else None
        except InputError as exc:
            out.append(na(str(exc)))
        for s in seqs:
            out.append(f"<h3>{esc(p.name)} / {esc(s.name)}</h3>")
            sc, notes = sequence_scene(s, mesh, opts.scope_frames)
            if mesh is None:
                notes.insert(0, f"airway mesh not drawn: no {show_path(mesh_path, opts.base)}")
            if not _path_points(sc):
                out.append(na(f"{s.name}: no trajectory, simulation or rendered poses to draw"))
                continue
            images = []
            for closeup, title in ((False, "overview (paths only)"),
                                   (True, "close-up: distal 30 mm, with the scope")):
                img, how = None, ""
                if pyvista_error is None:
                    try:
                        img = render_pyvista(sc, opts.view_size, closeup)
                        how = "pyvista (VTK, off-screen)"
                    except Exception as exc:  # any VTK/OpenGL failure: fall back, and say so
                        pyvista_error = f"{exc.__class__.__name__}: {exc}".splitlines()[0][:200]
                if img is None:
                    img = render_matplotlib(sc, opts.view_size, closeup)
                    how = f"matplotlib 3-D fallback (pyvista off-screen rendering unavailable: {pyvista_error})"
                images.append((title, img, how))
            figs = "".join(
                f'<figure>{img_tag(jpeg_uri(im), f"3-D {title} {s.name}", im.shape[1], im.shape[0])}'
                f"<figcaption>{esc(title)}; drawn by {esc(how)}</figcaption></figure>" for title, im, how in images)
            out.append(f'<div class="views">{figs}</div>')
            out.append(_legend(sc))
            out.append("<p class=\"note\">Anterior view (patient's right on the image left, superior up). "
                       + " ".join(esc(n[0].upper() + n[1:] + ".") for n in notes) + "</p>")
    return "\n".join(out) if out else na("no rendered sequence")
