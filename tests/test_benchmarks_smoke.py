"""Every benchmark's smoke mode runs (benchmarks/*.py): the scripts rot when the layout changes.

Each script runs as a subprocess from a scratch copy of ``benchmarks/`` whose ``src``, ``conf``,
``data`` and ``models`` are links to this checkout's, so ``ROOT`` (``parents[1]`` of the script) is the
scratch folder: whatever a run writes under ``benchmarks/results`` stays there and the published
results are never overwritten.  ``../shared`` is linked beside it, so the shared real data is found
the same way.  A script whose inputs are absent (a rendered default run in ``data/output``, Blender,
the shared data) is skipped with the reason.  ``NO_SMOKE`` lists the scripts without a smoke mode yet
and why; every script must be in one of the two tables.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"
#: a rendered default run (room run / dvc repro); ROOM_BENCH_RUN=DIR points the smoke runs at another one
#: (the scratch copy's data/output links to it; pose_eval, executor_throughput and the others only read it,
#: depth_eval writes its evaluation into it)
RUN = Path(os.environ.get("ROOM_BENCH_RUN") or REPO / "data" / "output")


def _has_run() -> bool:
    """A complete rendered run: a patient with its anatomy and a sequence whose render finished.

    A ``data/output`` left by a DVC run whose cached outputs are absent (a copy of the working tree holds the
    git-visible metrics and metadata but not the cached anatomy and frames) is not a run: every file the smoke
    scripts open first is checked, not only ``render.json``.
    """
    for render_json in RUN.glob("patient_*/sequence_*/metadata/render.json"):
        seq = render_json.parents[1]
        anatomy = seq.parent / "anatomy"
        if ((anatomy / "lung_model.obj").is_file() and (anatomy / "centreline_graph.json").is_file()
                and (seq / "metadata" / "simulation.json").is_file()
                and any((seq / "rgb").glob("*.png")) and any((seq / "depth").glob("*"))):
            return True
    return False


def _has_bpy() -> bool:
    try:
        import bpy  # noqa: F401
    except Exception:
        return False
    return True


NEEDS = {"run": (_has_run, f"no complete rendered default run in {RUN} (room run / dvc repro)"),
         "bpy": (_has_bpy, "Blender's bpy is not importable"),
         "shared": (lambda: (REPO.parent / "shared" / "data").is_dir(), "no ../shared/data")}

#: script -> (smoke arguments, what it needs)
SMOKE = {
    "config_validation.py": (["--repeats", "1"], ()),
    "texture_speed.py": (["--repeats", "1"], ()),
    "trajectory.py": (["--max-generation", "2"], ()),
    "navigation_sweep.py": (["--smoke"], ()),
    "phantom_vs_schmidt.py": (["--seeds", "1"], ()),
    "anatomy_speed.py": (["--sizes", "128"], ()),
    "anatomy_trachea_aspect.py": (["--quick"], ()),
    "noise.py": (["--speed-runs", "2", "--synth-frames", "2"], ("shared",)),
    "raycast_renderer.py": (["--frames", "2", "--write-frames", "1", "--repeats", "1"], ()),
    "pose_eval.py": (["--quick", "--methods", "orb_vo", "--data", str(RUN)], ("run",)),
    "depth_eval.py": (["--quick", "--data", str(RUN)], ("run",)),
    "executor_throughput.py": (["--quick", "--repeats", "1", "--max-wait", "0"], ("run",)),
    "realism_speed.py": (["--inputs", str(RUN), "--frames", "1"], ("run",)),
    "write_throughput.py": (["--quick"], ("run",)),
    "simulation.py": (["--quick"], ("run",)),
    "simulation_joint_plan.py": ([str(RUN), "--no-knobs"], ("run",)),
    "simulation_record_bytes.py": ([str(RUN)], ("run",)),
    "cycles_quality.py": (["--quick"], ("bpy", "run")),
    "cycles_reference.py": (["--quick"], ("bpy", "run")),
    "cycles_residual.py": (["--quick", "--direct"], ("bpy", "run")),
    "realism_indirect_pt.py": (["--quick", "--max-edge", "0,2.0"], ("run",)),
    "pipeline_timing.py": ([str(RUN), "--name", "pipeline_timing_smoke"], ("run",)),
}

#: scripts without a smoke mode (yet) -> why
NO_SMOKE = {
    "_synthetic.py": "a helper module, not a benchmark",
    "_throughput_parallel.py": "a helper module (the processes of write_throughput.py), not a benchmark",
    "realism_indirect.py": "renders Cycles references (bpy) at hundreds of samples; no size option below minutes",
    "realism_psnr_split.py": "renders Cycles references (bpy) of 16 tiles at 1024 and 256 spp per view; no size option "
                             "below minutes",
    "collision_speed.py": "simulates a real mask's route on several collision surfaces; minutes of PyBullet, no size option",
    "anatomy_memory.py": "runs the anatomy chain on a real mask up to a stage; no smaller input option",
    "real_tree_robustness.py": "the anatomy chain on perturbed real masks: minutes per case even for one",
    "reference_tree.py": ("the anatomy chain and its validation on the 3597-branch Schmidt tree's CT (about 4 min); "
                          "its stages run in tests/test_real_pipeline.py's exhaustive tier"),
    "collision_corridor.py": "no size option; owned by the collision work in progress",
    "collision_face_order.py": ("five whole simulations of the test phantom (minutes of PyBullet); it measures the "
                                "floor under test_collision_corridor, which runs the same code"),
    "evaluation_budget.py": "times the evaluation stages on a full default run",
    "medial_axis.py": "no size option below one phantom per seed",
    "mesh_decimation.py": "no options",
    "navigation.py": "closed-loop episodes; no size option",
    "navigation_contacts.py": "one whole closed-loop episode on a pipeline run's anatomy; no size option",
    "real_masks_chain.py": "the whole chain on every shared real mask",
    "realism.py": "needs a full default run and the real frames; no size option",
    "realism_refit.py": "renders two default sequences several times and runs the shared judges on the real "
                        "frames; minutes at any stride",
    "sdf_far_field.py": "a real mask at full size",
    "sdf_methods.py": "no options",
    "sequence_bytes.py": "measures a full rendered sequence on disk",
    "disk_usage.py": "measures a finished DVC workspace (run the pipeline first)",
    "dvc_noop.py": "times `dvc repro` in a finished DVC workspace (run the pipeline first)",
    "simcol_transfer.py": "fine-tunes the depth network on the SimCol sample; no size option",
}


def test_every_benchmark_is_listed():
    scripts = {p.name for p in BENCH.glob("*.py")}
    assert not (set(SMOKE) & set(NO_SMOKE))
    assert scripts == set(SMOKE) | set(NO_SMOKE), (
        f"not listed: {sorted(scripts - set(SMOKE) - set(NO_SMOKE))}; gone: {sorted((set(SMOKE) | set(NO_SMOKE)) - scripts)}")


def _scratch(tmp_path: Path) -> Path:
    root = tmp_path / "work" / "repo"
    (root / "benchmarks").mkdir(parents=True)
    for p in BENCH.glob("*.py"):
        shutil.copy2(p, root / "benchmarks" / p.name)
    for name in ("src", "conf", "models", "params.yaml", "dvc.yaml", "pyproject.toml"):
        if (REPO / name).exists():
            (root / name).symlink_to(REPO / name)
    (root / "data").mkdir()
    for p in (REPO / "data").iterdir() if (REPO / "data").is_dir() else []:
        if p.name != "output":
            (root / "data" / p.name).symlink_to(p)
    if RUN.is_dir():
        (root / "data" / "output").symlink_to(RUN.resolve())
    if (REPO.parent / "shared").exists():
        (tmp_path / "work" / "shared").symlink_to(REPO.parent / "shared")
    return root


#: smoke runs of minutes (1.5-2.3 min each at load 5, session 15): --exhaustive
EXHAUSTIVE_SMOKE = {"anatomy_speed.py", "config_validation.py", "noise.py"}


@pytest.mark.slow
@pytest.mark.parametrize("script", [s if s not in EXHAUSTIVE_SMOKE else pytest.param(s, marks=pytest.mark.exhaustive)
                                    for s in sorted(SMOKE)])
def test_benchmark_smoke(script, tmp_path):
    args, needs = SMOKE[script]
    for n in needs:
        ok, why = NEEDS[n]
        if not ok():
            pytest.skip(why)
    root = _scratch(tmp_path)
    # bpy (loaded first by conftest) sets the C locale in this process: decode the output as UTF-8 explicitly
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "src"), *filter(None, [os.environ.get("PYTHONPATH")])])}
    res = subprocess.run([sys.executable, str(root / "benchmarks" / script), *args], cwd=root, env=env,
                         capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=1800)
    assert res.returncode == 0, f"{script} {' '.join(args)}: exit {res.returncode}\n{res.stderr[-3000:]}"
