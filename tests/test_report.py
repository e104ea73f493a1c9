"""`room report`: the self-contained HTML page on a tiny dataset made by the real simulate and render
stages (a tube 'airway'), its images, its 'not available' lines, determinism, and a headless browser."""
from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest

from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
from room_pipeline.errors import InputError
from room_pipeline.io.atomic import write_json, write_text
from room_pipeline.io.mesh import write_obj
from room_pipeline.io.metrics import is_timing_file, read_metrics_file, timing_path
from room_pipeline.paths import PatientPaths
from room_pipeline.report import SECTIONS, ReportOptions, build_report, main, write_report
from room_pipeline.report import colour, common, draw3d, metrics, scene, tables
from tests.test_raycast import look, tube

MM = 1e-3
RADIUS = 8 * MM
N_FRAMES = 10
SIZE = 48
PATIENT = "patient_t"
RENDERED_SEQ, PLANNED_SEQ = "sequence_000", "sequence_001"
MODS = ["rgb", "depth", "relative_depth", "normals", "flow", "segmentation"]


def planned_frames(n: int = N_FRAMES, wiggle: float = 1.0) -> list[dict]:
    """Poses down the tube axis (+z), 2 mm apart, swaying 1 mm sideways; arclength as the planner writes it."""
    out, s, prev = [], 0.0, None
    for k in range(n):
        eye = np.array([wiggle * MM * np.sin(0.3 * k), 0.0, (5.0 + 2.0 * k) * MM])
        s += 0.0 if prev is None else float(np.linalg.norm(eye - prev))
        prev = eye
        pose = look(eye, (0.05 * np.cos(0.3 * k), 0.0, 1.0), down=(0.0, 1.0, 0.0))
        out.append({"index": k, "timestamp": 0.1 * k, "pose": pose.tolist(), "arclength": s})
    return out


def build_dataset(root: Path) -> Path:
    """<root>/patient_t: tube mesh + two-branch centreline; sequence_000 simulated (PyBullet) and rendered
    (fast renderer, 48 px, planned poses); sequence_001 planned only."""
    from omegaconf import OmegaConf

    from room_pipeline.stages import render, simulate

    paths = PatientPaths(root, PATIENT)
    write_obj(paths.mesh, tube(radius=RADIUS, z0=-5 * MM, z1=90 * MM, n_theta=32, n_z=30))
    write_obj(paths.collision_mesh, tube(radius=RADIUS, z0=-5 * MM, z1=90 * MM, n_theta=32, n_z=30))
    write_json(paths.mesh_metadata, {"report": {}})
    z0 = np.linspace(-5, 40, 7)[:, None] * MM
    z1 = np.linspace(40, 90, 8)[:, None] * MM
    graph = CentrelineGraph([GraphBranch(0, -1, 0, np.hstack([np.zeros((7, 2)), z0]), np.full(7, RADIUS)),
                             GraphBranch(1, 0, 1, np.hstack([np.zeros((8, 2)), z1]), np.full(8, RADIUS))])
    write_json(paths.centreline_graph, graph.to_dict())
    write_json(paths.sequence_metadata(RENDERED_SEQ) / "trajectory.json", {"frames": planned_frames()})
    write_json(paths.sequence_metadata(PLANNED_SEQ) / "trajectory.json", {"frames": planned_frames(6, 0.0)})
    cfg = OmegaConf.create({"output_dir": str(root), "simulate": {},
                            "render": {"width": SIZE, "height": SIZE, "fov_deg": 85.0, "modalities": MODS}})
    simulate.run(cfg, f"{PATIENT}/{RENDERED_SEQ}")
    render.run(cfg, f"{PATIENT}/{RENDERED_SEQ}")
    return root


def bench_dir(root: Path) -> Path:
    """Two benchmark results: a well-formed simulation.json and an sdf_methods.json of the wrong shape."""
    d = root / "bench"
    rows = [{"n_links": n, "time_step_s": dt, "tip_error_mm_max": e, "stable": e < 1.0,
             "wall_s_per_sim_s_free": w} for n, dt, e, w in
            [(5, 0.001, 0.35, 0.06), (5, 0.005, 0.35, 0.04), (10, 0.001, 0.09, 0.09), (10, 0.01, 5.0, 0.04)]]
    write_json(d / "simulation.json", {"speed_vs_error": rows})
    write_text(d / "simulation.md", "# Scope simulation benchmark\n\nmade up for the test\n")
    write_json(d / "sdf_methods.json", {"rows": [{"case": "c"}]})
    return d


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return build_dataset(tmp_path_factory.mktemp("out"))


@pytest.fixture(scope="module")
def opts(dataset) -> ReportOptions:
    return ReportOptions(output_dir=dataset, benchmarks_dir=bench_dir(dataset.parent),
                         tables_dir=dataset.parent / "no_reports", max_frames=3, view_size=(320, 260))


@pytest.fixture(scope="module")
def page(opts) -> str:
    return build_report(opts)


class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.imgs: list[dict] = []
        self.sections: list[str] = []
        self.external: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a)
        if tag == "section":
            self.sections.append(a.get("id"))
        if tag in ("link", "iframe", "object", "embed") or (tag == "script" and "src" in a):
            self.external.append(tag)


def parse(text: str) -> _Collect:
    c = _Collect()
    c.feed(text)
    return c


def decode(src: str) -> np.ndarray:
    m = re.fullmatch(r"data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)", src)
    assert m, src[:60]
    img = cv2.imdecode(np.frombuffer(base64.b64decode(m.group(2)), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def section(text: str, sid: str) -> str:
    m = re.search(rf'<section id="{sid}">(.*?)</section>', text, re.S)
    assert m, sid
    return m.group(1)


# --------------------------------------------------------------------------- the page


def test_all_sections_in_order_and_self_contained(page):
    c = parse(page)
    assert c.sections == [sid for sid, _ in SECTIONS]
    assert not c.external
    assert "http://" not in page and "https://" not in page
    assert "Content-Security-Policy" in page and 'data-images-loaded="pending"' in page
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")


def test_every_image_is_a_decodable_data_uri_of_its_stated_size(page):
    imgs = parse(page).imgs
    assert len(imgs) >= 3 * len(MODS) + 2 + 1          # thumbnails, two 3-D views, a plot
    for a in imgs:
        img = decode(a["src"])
        assert (img.shape[1], img.shape[0]) == (int(a["width"]), int(a["height"])), a["alt"]
        assert a["alt"]


def test_summary_counts_and_conventions(page):
    s = section(page, "summary")
    assert "1 patient(s), 1 rendered sequence(s)" in s
    assert f"{N_FRAMES} (open3d_raycast, simulated poses)" in s and f"{SIZE}x{SIZE}" in s
    assert PLANNED_SEQ not in s                  # planned only: not a sequence of the dataset (dataset reader)
    assert "RAS+" in s and "OpenCV: x right, y down, z forward" in s and "4x4 camera-to-world" in s


def test_discovery_lists_rendered_sequences_only(dataset):
    """Through the dataset reader: the planned-only sequence (trajectory.json, no render.json) is not listed."""
    from room_pipeline.report.discovery import find_patients, find_sequence_dirs

    assert (dataset / PATIENT / PLANNED_SEQ / "metadata" / "trajectory.json").is_file()
    assert find_patients(dataset) == [dataset / PATIENT]
    assert find_sequence_dirs(dataset / PATIENT) == [dataset / PATIENT / RENDERED_SEQ]


def test_thumbnails_one_column_per_modality_and_ranges(page):
    s = section(page, "thumbnails")
    for head in ("RGB (8-bit sRGB)", "depth, planar z (mm)", "relative inverse depth", "surface normals",
                 "optical flow", "segmentation"):
        assert head in s
    assert "frame_0000" in s and "frame_0009" in s                    # first and last of pick_frames(10, 3)
    lo, hi = map(float, re.search(r"([\d.]+) &larr; &rarr; ([\d.]+) mm", s).groups())
    assert 0 < lo < hi < 100                                          # mm inside a 95 mm tube
    assert "2 branch label(s)" in s
    assert PLANNED_SEQ not in s
    thumbs = [a for a in parse(s).imgs if re.fullmatch(r"(rgb|depth|flow) frame_\d{4}", a["alt"])]
    assert len(thumbs) == 3 * 3 and all(int(a["width"]) == SIZE for a in thumbs)


def test_view3d_draws_what_exists_and_says_what_not(page):
    s = section(page, "view3d")
    assert s.count("drawn by pyvista (VTK, off-screen)") == 2          # two views of the rendered sequence
    assert "Scope (tube, outer diameter 5.0 mm) at simulation frames" in s
    assert PLANNED_SEQ not in s                                        # the planned-only sequence is not listed
    assert "as simulated (the backbone simulation.json records)" in s


def test_metrics_table_lists_every_stage_file(page, dataset):
    s = section(page, "metrics")
    files = [f for f in sorted((dataset / PATIENT / "metrics").glob("*.json")) if not is_timing_file(f)]
    assert files and all(timing_path(f).is_file() for f in files)   # every stage writes its timings beside
    for f in files:
        doc = read_metrics_file(f)                                  # metrics + timings
        assert "wall_time_s" not in json.loads(f.read_text())       # the DVC metric holds no timing
        assert f"<td>{f.stem}</td>" in s
        assert f"<td>{common.fmt(doc['wall_time_s'])}</td>" in s
    assert "tracking_error_max_mm" in s and "<details>" in s and "total" in s


def test_benchmarks_plot_present_ones_and_explain_the_rest(page):
    s = section(page, "benchmarks")
    assert "Scope simulation: cost vs tip error" in s
    assert "not available: mesh_decimation: no mesh_decimation.json" in s
    assert "not available: sdf_methods.json has an unexpected structure" in s
    assert "simulation.md" in s and "Scope simulation benchmark" in s


def test_tables_not_generated_yet(page):
    assert "not available: not generated yet: no folder" in section(page, "tables")


def test_same_inputs_same_bytes(opts, page):
    assert build_report(opts) == page


# --------------------------------------------------------------------------- parts


def test_paper_tables_markdown_and_csv(tmp_path, opts):
    d = tmp_path / "reports"
    write_text(d / "table_1_pose.md", "### Table I: pose\n\n| Method | ATE (mm) | Status |\n|---|---:|---|\n"
                                      "| colmap | 0.31 | ok |\n| orb_vo | - | not run |\n\n"
                                      "- ATE after Sim(3) `umeyama`\n")
    write_text(d / "table_2_depth.csv", "Method,L1 (mm)\nzoe,1.5\n")
    write_text(d / "table_1_pose.csv", "ignored,because the md exists\n")
    s = tables.section_tables(ReportOptions(output_dir=opts.output_dir, tables_dir=d))
    assert "<h5>Table I: pose</h5>" in s
    assert '<th style="text-align:right">ATE (mm)</th>' in s and '<td style="text-align:right">0.31</td>' in s
    assert "<li>ATE after Sim(3) <code>umeyama</code></li>" in s
    assert "<td>zoe</td><td>1.5</td>" in s and "ignored" not in s
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "not generated yet: no table_*.md or table_*.csv" in tables.section_tables(
        ReportOptions(output_dir=opts.output_dir, tables_dir=empty))


def test_markdown_escapes_html():
    out = tables.markdown_to_html("# a <b>\n\nx & <script>y</script>\n")
    assert "<script>" not in out and "&lt;script&gt;" in out and "&lt;b&gt;" in out


def test_matplotlib_fallback_says_so(opts):
    s = draw3d.section_view3d(ReportOptions(output_dir=opts.output_dir, view_size=(200, 160), use_pyvista=False),
                          [opts.output_dir / PATIENT])
    assert s.count("matplotlib 3-D fallback (pyvista off-screen rendering unavailable: disabled") == 2   # one sequence
    for a in parse(s).imgs:
        assert decode(a["src"]).shape[:2] == (160, 200)


def test_metrics_absent_or_broken(tmp_path):
    p = tmp_path / "out" / "patient_x"
    (p / "anatomy").mkdir(parents=True)
    o = ReportOptions(output_dir=tmp_path / "out")
    assert "not available: no patient_x/metrics/*.json" in metrics.section_metrics(o, [p])
    write_text(p / "metrics" / "mesh.json", "{not json")
    s = metrics.section_metrics(o, [p])
    assert "not available: mesh.json is not readable JSON" in s


def test_empty_dataset_writes_a_page_of_not_available_lines(tmp_path):
    (tmp_path / "out").mkdir()
    out = write_report(ReportOptions(output_dir=tmp_path / "out"))
    text = out.read_text()
    assert out == tmp_path / "out" / "report.html"
    assert "not available: no patient folders" in text and "<img" not in text
    assert "not available: no benchmark results folder" in text


def test_missing_dataset_is_one_line_error(tmp_path, capsys):
    with pytest.raises(InputError) as exc:
        build_report(ReportOptions(output_dir=tmp_path / "nope"))
    assert "\n" not in str(exc.value) and "nope" in str(exc.value)
    assert main(["--output-dir", str(tmp_path / "nope"), "--out", str(tmp_path / "r.html")]) == 2
    assert capsys.readouterr().err.startswith("room: error: dataset folder not found")
    with pytest.raises(Exception):
        ReportOptions(output_dir=tmp_path, max_frames=0)


def test_main_writes_the_file(tmp_path, opts, capsys):
    out = tmp_path / "r" / "report.html"
    rc = main(["--output-dir", str(opts.output_dir), "--out", str(out), "--max-frames", "1",
               "--benchmarks-dir", str(tmp_path / "none"), "--tables-dir", str(tmp_path / "none")])
    assert rc == 0 and out.is_file()
    assert "room report: wrote" in capsys.readouterr().out
    assert len(re.findall(r'alt="rgb frame_\d{4}"', out.read_text())) == 1


def test_colour_maps():
    d = np.array([[0.0, 1.0], [2.0, 3.0]])
    c = colour.colorize(d, 1.0, 3.0, "viridis", valid=d > 0)
    assert c.dtype == np.uint8 and c.shape == (2, 2, 3)
    assert np.all(c[0, 0] == 0) and not np.array_equal(c[0, 1], c[1, 1])
    np.testing.assert_array_equal(c[0, 1], colour._lut("viridis")[0])
    np.testing.assert_array_equal(c[1, 1], colour._lut("viridis")[255])
    f = np.zeros((1, 3, 2))
    f[0, 0] = (2.0, 0.0)       # right: red
    f[0, 1] = (0.0, 4.0)       # down, beyond the maximum: saturated
    rgb = colour.flow_rgb(f, np.array([[True, True, False]]), 2.0)
    assert tuple(rgb[0, 0]) == (255, 0, 0) and rgb[0, 1].min() < 5 and np.all(rgb[0, 2] == 0)
    lab = colour.labels_rgb(np.array([[0, 1, 2, 1]]))
    assert np.all(lab[0, 0] == 0) and np.array_equal(lab[0, 1], lab[0, 3]) and not np.array_equal(lab[0, 1], lab[0, 2])
    n = colour.normals_rgb(np.array([[[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]], np.float32))
    assert tuple(n[0, 0]) == (128, 128, 0) and np.all(n[0, 1] == 0)
    assert colour.pick_frames(10, 3) == [0, 4, 9] and colour.pick_frames(2, 5) == [0, 1] and colour.pick_frames(0, 3) == []
    assert colour.thumbnail(np.zeros((40, 80, 3), np.uint8), 160).shape == (40, 80, 3)
    assert colour.thumbnail(np.zeros((300, 600), np.uint16), 150, nearest=True).shape == (75, 150)


def test_scope_backbone_is_the_recorded_one(dataset):
    """The report draws simulation.json's backbone (no robot model): its last point is the simulated tip."""
    import sys

    meta = dataset / PATIENT / RENDERED_SEQ / "metadata"
    sim = json.loads((meta / "simulation.json").read_text())
    lines, tips, picks = scene.scope_backbones(sim, 2)
    assert picks == [4, 9] and len(lines) == 2 and tips.shape == (2, 3)
    for line, tip, k in zip(lines, tips, picks):
        assert np.array_equal(line, np.asarray(sim["frames"][k]["backbone"]))
        assert np.allclose(tip, np.asarray(sim["frames"][k]["tip_pose"])[:3, 3], atol=1e-6)   # rounded to 1 um
        assert np.all(np.linalg.norm(line[:, :2], axis=1) < RADIUS)         # inside the tube
        assert len(line) >= 11                                               # 10 bending links + the tip
    old = {**sim, "frames": [{k: v for k, v in f.items() if k != "backbone"} for f in sim["frames"]]}
    with pytest.raises(InputError, match="rerun"):
        scene.scope_backbones(old, 2)
    # the report package imports no robot model (nor PyBullet)
    code = "import sys, room_pipeline.report; print(sorted(m for m in sys.modules if m.startswith(('room_pipeline.robot', 'pybullet'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8", check=True)
    assert out.stdout.strip() == "[]", out.stdout


# --------------------------------------------------------------------------- a real browser


def _chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no chromium binary on PATH (Debian: apt-get install -y --no-install-recommends chromium)")


def test_headless_chromium_loads_every_image_without_console_messages(tmp_path, page):
    exe = _chromium()
    f = tmp_path / "report.html"
    f.write_text(page, encoding="utf-8")
    shot = tmp_path / "shot.png"
    base = [exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=5000",
            "--enable-logging=stderr", "--v=0", "--hide-scrollbars", "--window-size=1280,2000"]
    dom = subprocess.run(base + ["--dump-dom", f.as_uri()], capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    n = len(parse(page).imgs)
    m = re.search(r'<body[^>]*data-images-loaded="([^"]*)"', dom.stdout)
    assert m and m.group(1) == f"{n}/{n}", (m and m.group(1), n)
    page_msgs = [ln for ln in dom.stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert not page_msgs, page_msgs
    run = subprocess.run(base + [f"--screenshot={shot}", f.as_uri()], capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=120)
    assert run.returncode == 0 and shot.is_file(), run.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img.shape == (2000, 1280, 3)
    assert (img < 200).any(axis=2).mean() > 0.02          # not a blank page: text and images drawn


def test_summary_row_says_how_far_from_the_target_the_scope_stopped_and_why(tmp_path):
    """Issue #18: a route that ends short of its target (Med-MPD's nodule outside the lumen, a narrowing)."""
    from room_pipeline.report.sections import _sequence_row

    meta = tmp_path / "p" / "sequence_000" / "metadata"
    meta.mkdir(parents=True)
    (meta / "trajectory.json").write_text(json.dumps({
        "frames": [{"pose": np.eye(4).tolist()}] * 3, "summary": {"length_m": 0.0421},
        "target": {"reached": False, "stop_distance": 0.01234, "stop_reason": "lumen_narrower_than_scope"}}))
    row = _sequence_row(meta.parent)
    assert "stopped 12.3 mm from the target (lumen_narrower_than_scope)" in row[2], row


def test_generated_paper_table_keeps_its_content():
    """The `tables` stage's Markdown, rendered by markdown-it-py: every header and cell text, the right
    alignment of the number columns and every note come through unchanged (the page's content).  The page
    shows what a CommonMark viewer shows (``*x*`` is emphasis there too; the old hand-written parser knew
    only code spans and ``**bold**``)."""
    from room_pipeline.evaluate.tables import Table

    t = Table("table_1_pose", "Table I: pose <ROOM>", ["Method", "RRA@5 (%)", "ATE (mm)", "Status"],
              [["colmap", "75.0", "0.31", "ok"], ["orb_vo_sift", "-", "1.20", "not run: a|b"]],
              ["ATE after Sim(3) `umeyama`; times in s/frame", "**bold** and <tags> & ampersands"], {})
    html_out = tables.markdown_to_html(t.to_markdown())

    class Cells(HTMLParser):
        def __init__(self):
            super().__init__()
            self.rows, self.cur, self.align, self.items, self.tag = [], None, [], [], None

        def handle_starttag(self, tag, attrs):
            if tag == "tr":
                self.cur = []
                self.rows.append(self.cur)
            if tag in ("td", "th"):
                self.cur.append("")
                self.align.append(dict(attrs).get("style"))
            if tag == "li":
                self.items.append("")
            self.tag = tag if tag in ("td", "th", "li") else self.tag

        def handle_endtag(self, tag):
            if tag in ("td", "th", "li"):
                self.tag = None

        def handle_data(self, data):
            if self.tag in ("td", "th"):
                self.cur[-1] += data
            elif self.tag == "li":
                self.items[-1] += data

    c = Cells()
    c.feed(html_out)
    assert c.rows == [t.header] + [[x.replace("|", "/") for x in r] for r in t.rows]
    assert "<h5>Table I: pose &lt;ROOM&gt;</h5>" in html_out and 'class="data"' in html_out
    right = [a == "text-align:right" for a in c.align[:4]]
    assert right == [a == "r" for a in t.align()]
    assert len(c.items) == 2 and "<code>umeyama</code>" in html_out and "<strong>bold</strong>" in html_out
    assert "&lt;tags&gt; &amp; ampersands" in html_out
