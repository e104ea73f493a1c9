"""Parallel executor (serial / local processes / Ray), the reproducibility manifest, and their use by the product.

The workload is a small render-and-write job shaped like the render stage:
the fast renderer on a tube, per-worker state = the renderer (built once),
exposure fixed once before the fan-out, frames written atomically into
rgb/ depth/ optical_flow/, then manifest.json.  It is module-level so that
spawned processes and Ray actors can import it, and runnable as a command
(``main``) for the kill / permission tests, which run it in a subprocess.
The real render stage through the executors, and `room run -m`, are at the end.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from room_pipeline.errors import ConfigError, InputError, RoomError
from room_pipeline.execution import (ExecutionParams, build_manifest, chunks, compare_manifests, compare_versions,
                                     ensure_writable, make_executor, read_manifest, remove_stale_temp_files,
                                     stale_temp_files, verify_manifest, write_manifest)
from room_pipeline.io.atomic import write_json, write_with
from room_pipeline.io.images import encode_flo, read_exr, read_flo, read_png, write_exr, write_flo, write_png8
from room_pipeline.io.mesh import Mesh

REPO = Path(__file__).resolve().parents[1]
MM = 1e-3
SIZE = 48
FOLDERS = ("rgb", "depth", "optical_flow")


# --------------------------------------------------------------------------- the workload


def tube_mesh(radius=5 * MM, length=80 * MM, n_theta=40, n_z=40) -> Mesh:
    """Open wobbly cylinder along +z, normals pointing out of the lumen."""
    th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    zs = np.linspace(-5 * MM, length, n_z)
    r = radius * (1 + 0.15 * np.sin(3 * th)[None, :] * np.cos(zs / (7 * MM))[:, None])
    v = np.stack([r * np.cos(th)[None, :], r * np.sin(th)[None, :], np.broadcast_to(zs[:, None], r.shape)], -1)
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    a, b = idx[:-1], np.roll(idx, -1, axis=1)[:-1]
    c, d = idx[1:], np.roll(idx, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    return Mesh(v.reshape(-1, 3), faces)


def poses(n: int) -> np.ndarray:
    """Camera-to-world poses advancing along the tube and turning slowly (non-trivial flow)."""
    out = np.repeat(np.eye(4)[None], n, axis=0)
    for i in range(n):
        a = 0.02 * i
        out[i, :3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
        out[i, :3, 3] = [0.5 * MM * np.sin(0.3 * i), 0.3 * MM, 0.6 * MM * i]
    return out


def make_scene(n: int, exposure_ev: float | None):
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.scene import Film, Scene

    return Scene(tube_mesh(), CameraIntrinsics.from_fov(SIZE, SIZE, 85.0), poses(n), np.arange(n) * 0.1,
                 face_labels=None, film=Film(exposure_ev=exposure_ev))


def make_state(out: str, n: int, exposure_ev: float, init_log: str | None, delay_s: float) -> dict:
    """Per-worker state: the renderer built once (logged to ``init_log`` to count initialisations)."""
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    token = uuid.uuid4().hex
    if init_log:
        with open(init_log, "a", encoding="utf-8") as fh:
            fh.write(f"{os.getpid()} {token}\n")
    return {"renderer": RaycastRenderer(make_scene(n, exposure_ev), RaycastConfig(nthreads=1)),
            "out": Path(out), "token": token, "delay_s": delay_s}


def render_frame(state: dict, i: int) -> dict:
    """Render frame i and write rgb / depth / flow atomically; the record for the metadata."""
    r, out = state["renderer"], state["out"]
    res = r.render(i, {"rgb", "depth", "flow"})
    name = f"frame_{i:04d}"
    write_png8(out / "rgb" / f"{name}.png", res["rgb"])
    write_exr(out / "depth" / f"{name}.exr", res["depth"], channels=("Y",), attributes={"units": "m"})
    if state["delay_s"]:                     # a slow writer: half the file, a pause, the rest (kill test)
        data = encode_flo(res["flow"])

        def slow(tmp: Path) -> None:
            tmp.write_bytes(data[: len(data) // 2])
            time.sleep(state["delay_s"])
            tmp.write_bytes(data)

        write_with(out / "optical_flow" / f"{name}.flo", slow)
    else:
        write_flo(out / "optical_flow" / f"{name}.flo", res["flow"])
    write_png8(out / "optical_flow" / f"valid_{i:04d}.png", res["flow_valid"].astype(np.uint8) * 255)
    return {"index": i, "hit_fraction": float(res["hit"].mean()), "pid": os.getpid(), "token": state["token"]}


def write_frames(out, n: int, backend: str = "serial", workers: int = 1, chunk_size: int = 0,
                 delay_s: float = 0.0, init_log: str | None = None) -> list[dict]:
    """The whole job: check the output location, clean a killed run's leftovers, fan out, write metadata + manifest."""
    from room_pipeline.render.raycast import RaycastRenderer

    out = Path(out)
    ensure_writable(out, *(out / f for f in FOLDERS))
    remove_stale_temp_files(out)
    ev = RaycastRenderer(make_scene(n, None)).exposure_ev          # once, before the fan-out
    params = ExecutionParams(backend=backend, workers=workers, chunk_size=chunk_size)
    with make_executor(params, init=(make_state, (str(out), n, ev, init_log, delay_s))) as ex:
        recs = ex.map(render_frame, range(n), desc="frames")
    write_json(out / "frames.json", {"exposure_ev": ev,
                                     "frames": [{k: r[k] for k in ("index", "hit_fraction")} for r in recs]})
    write_manifest(out, {"job": {"frames": n, "size": SIZE}, "execution": dataclasses.asdict(params)})
    return recs


def main(argv: list[str]) -> int:
    """``out n backend workers delay_s``: run :func:`write_frames`; a RoomError is one line on stderr, exit 2."""
    out, n, backend, workers, delay = argv
    try:
        write_frames(out, int(n), backend, int(workers), delay_s=float(delay))
    except RoomError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


def job_command(*args) -> list[str]:
    code = f"import sys; sys.path.insert(0, {str(REPO)!r}); from tests.test_execution import main; " \
           "sys.exit(main(sys.argv[1:]))"
    return [sys.executable, "-c", code, *map(str, args)]


# small module-level work functions (picklable by reference)


def add_offset(state, x):
    time.sleep(0.002 * ((x * 7) % 5))                 # scramble completion order
    return x + (state or 0)


def offset_factory(k):
    return k


def whoami(state, x):
    return (x, os.getpid(), state["token"])


def token_factory(log):
    token = uuid.uuid4().hex
    with open(log, "a", encoding="utf-8") as fh:
        fh.write(f"{os.getpid()} {token}\n")
    return {"token": token}


def thread_budget(state, x):
    """(executor's thread budget, BLAS / OpenMP pool sizes, OpenImageIO's EXR threads) seen in the worker."""
    import OpenImageIO as oiio
    from threadpoolctl import threadpool_info

    from room_pipeline.execution import worker_threads

    return (worker_threads(), sorted({p["num_threads"] for p in threadpool_info()}),
            oiio.get_int_attribute("exr_threads"))


def fail_on_three(state, x):
    if x == 3:
        raise InputError(f"item {x}: bad pose")
    return x


def die_on_two(state, x):
    if x == 2:
        os._exit(3)                                   # a worker killed (OOM killer, SIGKILL, segfault ...)
    return x


def failing_factory():
    raise ConfigError("render.width: must be >= 8")


def half_write_then_fail(state, x):
    """Writes through the atomic writer and fails half-way for x == 2: no file, no temporary may remain."""
    def writer(tmp: Path) -> None:
        tmp.write_bytes(b"partial")
        if x == 2:
            raise ValueError(f"item {x}: renderer failed")
        tmp.write_bytes(b"complete %d" % x)

    write_with(Path(state) / f"item_{x}.bin", writer)
    return x


# --------------------------------------------------------------------------- config and chunking


@given(n=st.integers(0, 300), workers=st.integers(1, 16), size=st.integers(0, 50))
@settings(max_examples=200, deadline=None)
def test_chunks_cover_the_items_in_order(n, workers, size):
    parts = chunks(n, workers, size)
    assert [i for r in parts for i in r] == list(range(n))
    assert all(len(r) > 0 for r in parts)
    if size > 0:
        assert all(len(r) == size for r in parts[:-1])
    elif n:
        assert len(parts) <= 4 * workers


def test_params_from_config_file_and_bad_values():
    import yaml

    doc = yaml.safe_load((REPO / "conf" / "execution" / "default.yaml").read_text())
    assert ExecutionParams.from_dict(doc) == ExecutionParams(backend="local", workers=0, ray_address=None,
                                                             chunk_size=0)
    p = ExecutionParams.from_dict({"backend": "ray", "workers": 4, "ray_address": "auto", "chunk_size": 8})
    assert (p.backend, p.workers, p.ray_address, p.chunk_size) == ("ray", 4, "auto", 8)
    for bad, msg in [({"backend": "dask"}, "execution.backend"), ({"workers": -1}, "execution.workers"),
                     ({"workers": 1.5}, "execution.workers"), ({"chunk_size": -1}, "execution.chunk_size"),
                     ({"ray_address": 6379}, "execution.ray_address"), ({"threads": 2}, "execution.threads")]:
        with pytest.raises(ConfigError, match=msg.replace(".", r"\.")) as ei:
            ExecutionParams.from_dict(bad)
        assert "\n" not in str(ei.value)


# --------------------------------------------------------------------------- serial and local processes


@pytest.mark.parametrize("backend", ["serial", "local"])
def test_order_preserved_and_state_used(backend):
    items = list(range(37))[::-1]
    with make_executor({"backend": backend, "workers": 2, "chunk_size": 3}, init=(offset_factory, (1000,))) as ex:
        assert ex.map(add_offset, items, desc="t") == [x + 1000 for x in items]
        assert ex.map(add_offset, []) == []


def test_local_workers_initialised_once_each(tmp_path):
    log = tmp_path / "init.log"
    with make_executor({"backend": "local", "workers": 2, "chunk_size": 1}, init=(token_factory, (str(log),))) as ex:
        first = ex.map(whoami, range(24))
        second = ex.map(whoami, range(24, 40))          # the same processes, no new initialisation
    assert [x for x, _, _ in first + second] == list(range(40))
    lines = [tuple(line.split()) for line in log.read_text().splitlines()]
    used = {(str(pid), tok) for _, pid, tok in first + second}
    assert used <= set(lines)
    pids = [pid for pid, _ in lines]
    assert 1 <= len(lines) <= 2 and len(set(pids)) == len(pids)      # one init per process, at most 2 processes
    assert str(os.getpid()) not in pids


@pytest.mark.parametrize("backend", ["serial", "local"])
def test_errors_propagate_as_the_original_exception(backend, tmp_path):
    with make_executor({"backend": backend, "workers": 2, "chunk_size": 2}) as ex:
        with pytest.raises(InputError) as ei:
            ex.map(fail_on_three, range(10))
        assert str(ei.value) == "item 3: bad pose"
    with make_executor({"backend": backend, "workers": 2, "chunk_size": 1}, init=(str, (tmp_path,))) as ex:
        with pytest.raises(ValueError, match=r"^item 2: renderer failed$"):
            ex.map(half_write_then_fail, range(6))
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "item_2.bin" not in names and not stale_temp_files(tmp_path)      # no partial file, no temporary
    for p in tmp_path.iterdir():
        assert p.read_bytes() == b"complete %d" % int(p.stem.split("_")[1])
    with make_executor({"backend": backend, "workers": 2}, init=(failing_factory, ())) as ex:
        with pytest.raises(ConfigError, match=r"^render\.width: must be >= 8$"):
            ex.map(fail_on_three, range(4))


def test_dead_worker_is_a_room_error_and_the_executor_recovers():
    with make_executor({"backend": "local", "workers": 2, "chunk_size": 1}) as ex:
        with pytest.raises(RoomError, match=r"^t: a worker process of the local executor died"):
            ex.map(die_on_two, range(6), desc="t")
        assert ex.map(die_on_two, [0, 1, 3]) == [0, 1, 3]          # a new pool


def test_workers_limit_library_threads():
    """Each local worker limits BLAS/OpenMP and OpenImageIO to threads_per_worker; serial leaves them alone."""
    assert ExecutionParams(workers=2, threads_per_worker=3).threads == 3
    assert ExecutionParams(workers=64).threads == 1
    assert ExecutionParams(workers=1).threads == max(1, os.cpu_count() or 1)
    with pytest.raises(ConfigError, match="threads_per_worker"):
        ExecutionParams(threads_per_worker=-1)
    with make_executor(ExecutionParams(backend="local", workers=2, threads_per_worker=1)) as ex:
        seen = ex.map(thread_budget, range(4))
    assert all(t == 1 and pools == [1] and exr == 1 for t, pools, exr in seen), seen
    with make_executor(ExecutionParams(backend="serial")) as ex:
        assert ex.map(thread_budget, [0])[0][0] is None


def test_local_rejects_what_cannot_reach_a_process():
    with make_executor({"backend": "local", "workers": 1}) as ex:
        with pytest.raises(TypeError, match="module-level function"):
            ex.map(lambda s, x: x, [1])


# --------------------------------------------------------------------------- byte-identical outputs


def test_serial_and_local_write_identical_bytes(tmp_path):
    n = 10
    write_frames(tmp_path / "a", n, "serial")
    write_frames(tmp_path / "b", n, "serial")
    recs = write_frames(tmp_path / "c", n, "local", workers=2, chunk_size=3)
    assert len({r["pid"] for r in recs}) >= 1 and os.getpid() not in {r["pid"] for r in recs}
    # two serial runs: the manifests themselves are byte-identical
    assert (tmp_path / "a" / "manifest.json").read_bytes() == (tmp_path / "b" / "manifest.json").read_bytes()
    a, c = read_manifest(tmp_path / "a"), read_manifest(tmp_path / "c")
    assert len(a["files"]) == 4 * n + 1 and compare_manifests(a, c) == [] and compare_versions(a, c) == []
    assert a["config"]["execution"]["backend"] == "serial" and c["config"]["execution"]["backend"] == "local"
    for d in "abc":
        assert verify_manifest(tmp_path / d) == []
    assert read_png(tmp_path / "c" / "rgb" / "frame_0004.png").shape == (SIZE, SIZE, 3)
    assert read_flo(tmp_path / "c" / "optical_flow" / "frame_0004.flo").shape == (SIZE, SIZE, 2)


# --------------------------------------------------------------------------- manifest


def test_manifest_lists_every_file_and_catches_changes(tmp_path):
    root = tmp_path / "ds"
    (root / "b" / "c").mkdir(parents=True)
    (root / "b" / "c" / "z.bin").write_bytes(b"\x00" * 1000)
    (root / "a.txt").write_text("hello")
    (root / "b" / "y.json").write_text("{}")
    cfg = {"render": {"width": 600, "modalities": ("rgb", "depth")}, "execution": {"backend": "local"},
           "out": Path("/x")}
    path = write_manifest(root, cfg, extra={"note": "test"})
    doc = json.loads(path.read_text())
    assert [f["path"] for f in doc["files"]] == ["a.txt", "b/c/z.bin", "b/y.json"]
    assert doc["files"][0]["sha256"] == "2cf24dba5fb0a30e26e83b2ac5b9e29e1b161e5c1fa7425e73043362938b9824"
    assert doc["files"][1]["size"] == 1000
    assert doc["config"]["render"]["modalities"] == ["rgb", "depth"] and doc["config"]["out"] == "/x"
    assert doc["versions"]["numpy"] == np.__version__ and "python" in doc["versions"] and "torch" in doc["versions"]
    assert doc["extra"] == {"note": "test"} and doc["platform"]["system"]
    assert verify_manifest(root) == [] and build_manifest(root, cfg)["files"] == doc["files"]  # manifest not listed

    # truncated, altered, missing, extra (a writer's leftover temporary) files are all reported
    (root / "b" / "c" / "z.bin").write_bytes(b"\x00" * 400)
    (root / "a.txt").write_text("hellO")
    (root / "b" / "y.json").unlink()
    (root / "b" / ".y.json.abcd1234.tmp.json").write_text("{")
    problems = verify_manifest(root)
    assert problems == ["content differs: a.txt", "size differs (truncated?): b/c/z.bin (400 bytes, manifest 1000)",
                        "missing: b/y.json", "not in the manifest: b/.y.json.abcd1234.tmp.json"]
    assert verify_manifest(root, strict=False) == problems[:3]
    assert stale_temp_files(root) == [root / "b" / ".y.json.abcd1234.tmp.json"]
    assert remove_stale_temp_files(root) and not stale_temp_files(root)

    other = build_manifest(root, {**cfg, "render": {"width": 300, "modalities": ["rgb", "depth"]},
                                  "execution": {"backend": "ray"}})
    diffs = compare_manifests(doc, other)
    assert "file missing in the second: b/y.json" in diffs
    assert any(d.startswith("file differs: a.txt") for d in diffs)
    assert any(d.startswith("file differs: b/c/z.bin") and "1000 vs 400 bytes" in d for d in diffs)
    assert "config render.width: 600 vs 300" in diffs
    assert not any("execution" in d for d in diffs)                  # the backend must not matter
    assert any("execution" in d for d in compare_manifests(doc, other, ignore_config=()))
    ignored = compare_manifests(doc, other, ignore_files=("b/*", "*.txt"))
    assert not any(d.startswith("file") for d in ignored) and "config render.width: 600 vs 300" in ignored
    assert compare_versions(doc, {**doc, "versions": {**doc["versions"], "numpy": "2.0.0"}}) == \
        [f"versions numpy: {np.__version__} vs 2.0.0"]


def test_temp_file_pattern_matches_only_the_atomic_writers_names(tmp_path):
    from room_pipeline.io.atomic import atomic_path

    with atomic_path(tmp_path / "frame_0001.exr") as tmp:
        tmp.write_bytes(b"x")
        assert stale_temp_files(tmp_path) == [tmp]              # what a SIGKILL here would leave behind
    for name in [".hidden", ".frame.png", "frame_0001.exr", ".frame_0002.png.abcdefgh.tmp.exr", ".a.b.tmp"]:
        (tmp_path / name).write_bytes(b"keep")
    assert stale_temp_files(tmp_path) == []


def test_manifest_errors(tmp_path):
    with pytest.raises(InputError, match="manifest not found"):
        verify_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{\"format\": \"other\"}")
    with pytest.raises(InputError, match="not a room-manifest/1 manifest"):
        read_manifest(tmp_path)
    with pytest.raises(InputError, match="is not a folder"):
        build_manifest(tmp_path / "nope", {})


# --------------------------------------------------------------------------- killed, unwritable, full


def _frames_written(out: Path) -> int:
    d = out / "rgb"
    return len([p for p in d.glob("frame_*.png")]) if d.is_dir() else 0


def test_sigkill_mid_run_then_rerun_completes_intact(tmp_path):
    out, n = tmp_path / "killed", 24
    # each .flo takes 0.3 s to write: kill once 4 frames are done and a half-written temporary is on disk
    proc = subprocess.Popen(job_command(out, n, "local", 2, 0.3), start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    while (_frames_written(out) < 4 or not stale_temp_files(out)) and proc.poll() is None \
            and time.monotonic() - t0 < 120:
        time.sleep(0.01)
    assert proc.poll() is None, f"the job ended before it could be killed: {proc.stderr.read().decode()[-500:]}"
    os.killpg(proc.pid, signal.SIGKILL)               # the parent and its worker processes, mid-write
    proc.wait()
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    assert 4 <= _frames_written(out) < n and not (out / "manifest.json").exists()
    left = stale_temp_files(out)
    assert left and all(p.stat().st_size < 12 + 8 * SIZE * SIZE for p in left)     # half-written .flo files
    # the job again (here in-process) completes; the killed run's temporaries are gone, every file is whole
    write_frames(out, n, "serial")
    assert verify_manifest(out) == [] and stale_temp_files(out) == []
    write_frames(tmp_path / "reference", n, "serial")
    assert compare_manifests(read_manifest(tmp_path / "reference"), read_manifest(out)) == []
    depth, names, _ = read_exr(out / "depth" / f"frame_{n - 1:04d}.exr")
    assert names == ("Y",) and depth.shape == (SIZE, SIZE)


def _tree_bytes(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _assert_refused_cleanly(res: subprocess.CompletedProcess, out: Path, before: dict, reason: str) -> None:
    assert res.returncode == 2, res.stderr[-2000:]
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: output folder {out}") and "not writable" in lines[0]
    assert reason in lines[0]
    assert _tree_bytes(out) == before and verify_manifest(out) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="running as root: permissions are not enforced for root")
def test_unwritable_output_location_is_a_clear_error(tmp_path):
    out = tmp_path / "ds"
    write_frames(out, 3, "serial")
    before = _tree_bytes(out)
    for d, _, _ in os.walk(out):
        os.chmod(d, 0o500)
    try:
        res = subprocess.run(job_command(out, 5, "serial", 1, 0.0), capture_output=True, text=True, timeout=120)
    finally:
        for d, _, _ in os.walk(out):
            os.chmod(d, 0o700)
    _assert_refused_cleanly(res, out, before, "Permission denied")


def test_read_only_output_location_is_a_clear_error(tmp_path):
    """The same for a read-only file system: the job runs in a mount namespace where the folder is a ro bind mount."""
    mount_ro = 'mount --bind -o ro "$1" "$1" && shift && exec "$@"'
    probe = subprocess.run(["unshare", "-m", "sh", "-c", mount_ro, "sh", str(tmp_path), "true"],
                           capture_output=True) if shutil.which("unshare") else None
    if probe is None or probe.returncode != 0:
        pytest.skip("cannot make a read-only bind mount here (needs unshare and CAP_SYS_ADMIN, e.g. root)")
    out = tmp_path / "ds"
    write_frames(out, 3, "serial")
    before = _tree_bytes(out)
    res = subprocess.run(["unshare", "-m", "sh", "-c", mount_ro, "sh", str(out), *job_command(out, 5, "serial", 1, 0)],
                         capture_output=True, text=True, timeout=120)
    _assert_refused_cleanly(res, out, before, "Read-only file system")


def test_ensure_writable_in_process(tmp_path):
    ensure_writable(tmp_path / "new" / "deep")
    assert (tmp_path / "new" / "deep").is_dir() and not list((tmp_path / "new" / "deep").iterdir())
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match=r"output folder .*file/sub is not writable"):
        ensure_writable(tmp_path / "file" / "sub")
    with pytest.raises(InputError, match="MB free, about"):
        ensure_writable(tmp_path, need_bytes=1 << 62)


def test_full_output_location_keeps_what_was_written(tmp_path):
    """A write failing half-way through a run (file-size limit: a full disk as seen by a writer)."""
    out = tmp_path / "full"
    write_frames(out, 4, "serial")
    before = _tree_bytes(out)
    limit = (out / "optical_flow" / "frame_0000.flo").stat().st_size - 1   # PNGs and EXRs fit, a .flo does not
    code = (f"import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit})); "
            f"sys.path.insert(0, {str(REPO)!r}); from tests.test_execution import main; sys.exit(main(sys.argv[1:]))")
    res = subprocess.run([sys.executable, "-c", code, str(out), "4", "local", "1", "0"], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 2, res.stderr[-2000:]
    last = res.stderr.strip().splitlines()[-1]       # the worker's failed write, one line naming the file and why
    assert last == f"error: cannot write {out / 'optical_flow' / 'frame_0000.flo'}: File too large"
    assert _tree_bytes(out) == before and verify_manifest(out) == [] and not stale_temp_files(out)


# --------------------------------------------------------------------------- Ray


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'ray[default]')")
    ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False,
             configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_backend(ray_session, tmp_path):
    ray = ray_session
    log = tmp_path / "init.log"
    with make_executor({"backend": "ray", "workers": 2, "chunk_size": 2}, init=(token_factory, (str(log),))) as ex:
        got = ex.map(whoami, list(range(30))[::-1])
        assert [x for x, _, _ in got] == list(range(30))[::-1]
        lines = [tuple(line.split()) for line in log.read_text().splitlines()]
        assert len(lines) == 2 and {(str(p), t) for _, p, t in got} <= set(lines)   # one init per actor
        assert sorted(int(p) for p, _ in lines) == sorted(ex.actor_pids())
        with pytest.raises(InputError) as ei:
            ex.map(fail_on_three, range(8))
        assert str(ei.value) == "item 3: bad pose" and type(ei.value) is InputError
        assert [x for x, _, _ in ex.map(whoami, [5, 6])] == [5, 6]                    # still usable afterwards
        with pytest.raises(RoomError, match="a Ray worker failed"):
            ex.map(die_on_two, range(4))
        assert [x for x, _, _ in ex.map(whoami, [7])] == [7]       # new actors
    assert ray.is_initialized()                       # a session it joined is left running
    with make_executor({"backend": "ray", "workers": 1}, init=(failing_factory, ())) as ex:
        with pytest.raises(ConfigError, match=r"^render\.width: must be >= 8$"):
            ex.map(add_offset, range(3))
    recs = write_frames(tmp_path / "ray", 10, "ray", workers=2, chunk_size=3)
    assert len({r["pid"] for r in recs}) == 2
    write_frames(tmp_path / "serial", 10, "serial")
    ms, mr = read_manifest(tmp_path / "serial"), read_manifest(tmp_path / "ray")
    assert mr["config"]["execution"]["backend"] == "ray"
    assert compare_manifests(ms, mr) == [] and verify_manifest(tmp_path / "ray") == []


def test_ray_missing_is_a_clear_error(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    from room_pipeline.errors import BackendUnavailable

    with pytest.raises(BackendUnavailable, match="needs the 'ray' package"):
        make_executor({"backend": "ray"})


# --------------------------------------------------------------------------- the render stage through the executor


def _rendered(root: Path) -> dict:
    """Every file the render stage wrote (bytes), without the metrics (wall times)."""
    return {k: v for k, v in _tree_bytes(root).items() if "/metrics/" not in f"/{k}"}


def _render_again(ref_root: Path, root: Path, render: dict, execution: dict | None) -> dict:
    """The inputs of ``ref_root`` (mesh, centreline, poses) rendered again into ``root`` with another executor."""
    from omegaconf import OmegaConf

    from room_pipeline.stages import render as render_stage
    from tests.test_dataset import PATIENT, SEQUENCE

    shutil.copytree(ref_root, root)
    seq = root / PATIENT / SEQUENCE
    for d in seq.iterdir():
        if d.name != "metadata":
            shutil.rmtree(d)
    (seq / "metadata" / "render.json").unlink()
    shutil.rmtree(root / PATIENT / "metrics")
    (seq / "rgb").mkdir()
    stale = seq / "rgb" / ".frame_0000.png.k1ll3d00.tmp.png"       # what a killed run leaves: removed first
    stale.write_bytes(b"half")
    cfg = {"output_dir": str(root), "render": render}
    if execution is not None:
        cfg["execution"] = execution
    metrics = render_stage.run(OmegaConf.create(cfg), f"{PATIENT}/{SEQUENCE}")
    assert not stale.exists()
    return metrics


@pytest.fixture(scope="module")
def rendered_serial(tmp_path_factory):
    """The render stage with its default execution (local, 1 worker: in-process) on a small tube sequence."""
    from tests.test_dataset import FOV, RENDERED, render_sequence

    root = tmp_path_factory.mktemp("serial")
    render_sequence(root, n=7, size=32)
    return root, {"width": 32, "height": 32, "fov_deg": FOV, "modalities": list(RENDERED), "poses": "planned"}


@pytest.mark.parametrize("backend", ["local", "ray"])
def test_render_stage_bytes_do_not_depend_on_the_executor(rendered_serial, tmp_path, backend, request):
    """Two workers (frames in 3 chunks, Open3D on one thread each) write the bytes of the serial run, render.json too."""
    if backend == "ray":
        request.getfixturevalue("ray_session")
    ref, render = rendered_serial
    metrics = _render_again(ref, tmp_path / backend, render, {"backend": backend, "workers": 2, "chunk_size": 3})
    a, b = _rendered(ref), _rendered(tmp_path / backend)
    # 7 files a frame (point clouds on demand); legend, camera, render.json, point_clouds.json, the
    # sequence_index record (sha256 of the frames); 3 inputs
    assert len(a) == 7 * 7 + 8 and sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []
    assert metrics["frames"] == 7 and metrics["workers"] == 2 and metrics["peak_rss_mb"] > 0
    meta = json.loads(b["patient_t/sequence_000/metadata/render.json"])
    assert meta["renderer"]["config"]["nthreads"] == 0              # the metadata is the driver's, whatever the workers
    assert meta["renderer"]["film"]["exposure_ev"] is None and isinstance(meta["renderer"]["exposure_ev"], float)


def test_render_stage_execution_params():
    from omegaconf import OmegaConf

    from room_pipeline.render.sequence import execution_params

    assert execution_params(OmegaConf.create({}), frames=8).backend == "serial"   # no section, few frames: in-process
    assert execution_params(OmegaConf.create({"execution": {"backend": "local", "workers": 1}})).backend == "serial"
    p = execution_params(OmegaConf.create({"execution": {"backend": "local", "workers": 3}}))
    assert (p.backend, p.workers) == ("local", 3)
    with pytest.raises(ConfigError, match=r"^execution\.workers must be >= 1"):
        execution_params(OmegaConf.create({"execution": {"workers": -1}}))
    # workers 0 (the default): one per usable core, at most one per MIN_ITEMS_PER_WORKER frames
    from room_pipeline.execution.executor import MIN_ITEMS_PER_WORKER, usable_cores

    auto = OmegaConf.create({"execution": {"backend": "local", "workers": 0}})
    assert execution_params(auto, frames=MIN_ITEMS_PER_WORKER - 1).backend == "serial"     # too few frames: in-process
    big = execution_params(auto, frames=10_000)
    assert big.workers == usable_cores() and big.backend == ("local" if usable_cores() > 1 else "serial")
    assert execution_params(auto, frames=2 * MIN_ITEMS_PER_WORKER).workers == min(2, usable_cores())
    assert ExecutionParams(workers=0).resolved().workers == usable_cores()
    assert ExecutionParams(workers=3).resolved(1).workers == 3                           # explicit: kept
    assert ExecutionParams(workers=0).threads == max(1, (os.cpu_count() or 1) // usable_cores())


def test_render_stage_cycles_bytes_do_not_depend_on_the_executor(tmp_path):
    """Cycles RGB (exposure chosen once in the driver, Cycles threads = cores / workers) in worker processes.

    The driver imported bpy first: a spawned worker must still import it (see room_pipeline.render.blender.import_bpy).
    """
    pytest.importorskip("bpy")
    from tests.test_dataset import FOV, render_sequence

    render = {"width": 24, "height": 24, "fov_deg": FOV, "modalities": ["rgb", "depth"], "backend": "cycles",
              "cycles_samples": 4, "poses": "planned"}
    ref = tmp_path / "ref"
    render_sequence(ref, n=3, size=24, modalities=("rgb", "depth"))
    serial = tmp_path / "serial"
    _render_again(ref, serial, render, {"backend": "serial"})
    _render_again(serial, tmp_path / "local", render, {"backend": "local", "workers": 2, "chunk_size": 1})
    a, b = _rendered(serial), _rendered(tmp_path / "local")
    assert sorted(a) == sorted(b) and [k for k in a if a[k] != b[k]] == []
    meta = json.loads(b["patient_t/sequence_000/metadata/render.json"])
    assert meta["renderer"]["rgb"]["backend"] == "blender_cycles"
    assert meta["renderer"]["rgb"]["settings"]["threads"] == 0 and meta["renderer"]["rgb"]["settings"]["exposure"] is None


# --------------------------------------------------------------------------- room run -m (Hydra multirun)


def _hydra_quiet() -> list[str]:
    return ["hydra/job_logging=none", "hydra/hydra_logging=none"]


def test_room_run_multirun_runs_one_job_per_sweep_point(tmp_path, monkeypatch, capsys):
    from omegaconf import OmegaConf

    from room_pipeline import cli
    from room_pipeline.config.compose import compose

    monkeypatch.delenv("ROOM_CONF_DIR", raising=False)
    monkeypatch.chdir(REPO)
    seen = []

    def fake_run(cfg, patient=None, until=None):
        seen.append((OmegaConf.to_container(cfg), patient, until, os.getcwd()))
        return 0

    monkeypatch.setattr(cli, "run_pipeline", fake_run)
    sweep = tmp_path / "sweep"
    rc = cli.main(["run", "-m", "--until", "mesh", "render.width=32,64", "execution.workers=2",
                   f"hydra.sweep.dir={sweep}", *_hydra_quiet()])
    assert rc == 0
    assert [c["render"]["width"] for c, _, _, _ in seen] == [32, 64]
    assert all(u == "mesh" and p is None and cwd == str(REPO) for _, p, u, cwd in seen)
    # each job gets exactly what `room run` composes for its point of the sweep (relative output_dir, no hydra node)
    assert seen[0][0] == OmegaConf.to_container(compose(["render.width=32", "execution.workers=2"]))
    assert seen[1][0]["output_dir"] == "data/output" and "hydra" not in seen[1][0]
    assert (sweep / "0" / ".hydra" / "overrides.yaml").is_file() and (sweep / "1" / ".hydra").is_dir()

    # a failed job ends the sweep with its exit status; a RoomError is one line and exit status 2
    calls = []

    def failing(cfg, patient=None, until=None):
        calls.append(cfg.render.width)
        if cfg.render.width == 32:
            return 3
        return 0

    monkeypatch.setattr(cli, "run_pipeline", failing)
    assert cli.main(["run", "-m", "render.width=32,64", f"hydra.sweep.dir={tmp_path / 's2'}", *_hydra_quiet()]) == 3
    assert calls == [32]

    def bad_patient(cfg, patient=None, until=None):
        raise RoomError(f"unknown patient {patient!r}")

    monkeypatch.setattr(cli, "run_pipeline", bad_patient)
    capsys.readouterr()
    assert cli.main(["run", "-m", "--patient", "nobody", "render.width=32",
                     f"hydra.sweep.dir={tmp_path / 's3'}", *_hydra_quiet()]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == "room: error: unknown patient 'nobody'"
