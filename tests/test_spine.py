"""The pipeline spine: config composition, dvc.yaml exactness, CLI behaviour on bad input."""
from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from room_pipeline import stages
from room_pipeline.config.compose import compose, compose_yaml
from room_pipeline.io.metrics import timing_path
from room_pipeline.paths import PatientPaths

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import stage_deps  # noqa: E402
import write_dvc_yaml  # noqa: E402


def test_params_yaml_is_fresh_composition_of_conf():
    """params.yaml must equal what `dvc exp run` would compose from conf/ (run `room params`)."""
    assert (REPO / "params.yaml").read_text(encoding="utf-8") == compose_yaml(conf_dir=REPO / "conf")


def test_compose_matches_dvc_own_composition(tmp_path):
    """`room params` and `dvc exp run -S ...` write the same bytes (same overrides)."""
    from dvc.utils.hydra import compose_and_dump

    overrides = ["output_dir=elsewhere", "patients=phantom_cohort"]
    out = tmp_path / "params.yaml"
    compose_and_dump(out, str(REPO / "conf"), None, "config", str(REPO), overrides)
    assert out.read_text(encoding="utf-8") == compose_yaml(overrides, conf_dir=REPO / "conf")


def test_dvc_yaml_is_generated_from_stage_table():
    assert (REPO / "dvc.yaml").read_text(encoding="utf-8") == write_dvc_yaml.render(), \
        "dvc.yaml is stale: run `python scripts/write_dvc_yaml.py`"


# One subprocess reports every stage's import closure: before each stage every ``room_pipeline`` module is
# dropped from ``sys.modules``, so ``import room_pipeline.cli, room_pipeline.stages.<name>`` loads exactly the
# project modules a fresh process would (third-party modules stay loaded: they are not in the closure, and
# loading them once instead of once per stage is what makes this cheap).
_CLOSURES = """
import importlib, json, sys
out = {}
for name in sys.argv[1:]:
    for k in [k for k in sys.modules if k.startswith('room_pipeline')]:
        del sys.modules[k]
    importlib.import_module('room_pipeline.cli')
    importlib.import_module('room_pipeline.stages.' + name)
    out[name] = sorted(k for k in sys.modules if k.startswith('room_pipeline'))
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def import_closures() -> dict[str, list[str]]:
    """stage name -> the ``room_pipeline`` modules that importing the CLI and that stage's module loads."""
    import json

    r = subprocess.run([sys.executable, "-c", _CLOSURES, *stages.STAGES], capture_output=True, text=True,
                       encoding="utf-8", check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_import_closures_are_per_stage(import_closures):
    """The one-process closures do not leak between stages: a light stage's closure lacks a heavy one's modules."""
    assert "room_pipeline.stages.render" in import_closures["render"]
    assert "room_pipeline.stages.render" not in import_closures["tables"]
    assert all(f"room_pipeline.stages.{n}" in c for n, c in import_closures.items())
    assert sum(len(c) for c in import_closures.values()) > len(set().union(*import_closures.values()))


@pytest.mark.parametrize("name", stages.STAGES)
def test_dvc_stage_lists_exactly_its_code_deps(name, import_closures):
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())
    st = dvc["stages"][name]
    deps = [d for d in st.get("do", st)["deps"] if d.startswith("src/")]
    assert sorted(deps) == stage_deps.package_deps(name)
    # and the closure is what Python really imports for that stage
    out = import_closures[name]
    imported = {str(Path(importlib.util.find_spec(m).origin).relative_to(REPO)) for m in out}
    covered = lambda f: any(f == d or f.startswith(d + "/") for d in deps)  # noqa: E731  (a file, or in a folder)
    assert all(map(covered, imported)), f"imported but not listed: {sorted(f for f in imported if not covered(f))}"
    # the package-level list is exactly the packages of the import closure (no folder listed for nothing)
    files = stage_deps.stage_deps(name)
    assert all(any(f == d or f.startswith(d + "/") for f in files) for d in deps)


@pytest.mark.parametrize("name", stages.STAGES)
def test_dvc_stage_outs_match_stage_module(name):
    """dvc.yaml outs/metrics == what the stage module says it writes; params keys exist."""
    cfg = compose(conf_dir=REPO / "conf")
    st = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"][name]
    module = stages.load(name)
    fan = stages.FAN_OUT[name]
    if fan == "sequences":
        body, keys = st, [(p, s) for p in cfg.patients for s in cfg.sequences]
    elif fan == "dataset":
        body, keys = st, [("all", None)]
    elif fan == "training":
        body, keys = st, [(cfg.depth.cnn.checkpoint_patient, None)]
        assert st["cmd"].startswith(f"room stage {name} --patient ${{depth.cnn.checkpoint_patient}}")
    else:
        assert st["foreach"] == "${%s}" % fan
        body, keys = st["do"], [(k, None) for k in (cfg.phantoms if fan == "phantoms" else cfg.patients)]
    assert keys, f"{name}: nothing to fan out over in the default config"
    for patient, seq in keys:
        def render(s: str) -> str:
            s = s.replace("${output_dir}", cfg.output_dir).replace("${key}", patient)
            s = s.replace("${depth.cnn.checkpoint_patient}", cfg.depth.cnn.checkpoint_patient)
            s = s.replace("${evaluate.tables.output_dir}", cfg.evaluate.tables.output_dir)
            return s.replace("${item.patient}", patient).replace("${item.sequence}", seq or "")
        outs = {render(next(iter(o)) if isinstance(o, dict) else o)
                for o in body.get("outs", []) + body.get("plots", [])}
        metrics = {render(next(iter(m))) if isinstance(m, dict) else render(m) for m in body["metrics"]}
        key = f"{patient}/{seq}" if seq else patient
        # every stage also writes its timings beside its metrics: an uncached out, not a metric
        timings = {str(timing_path(m)) for m in metrics}
        assert outs | metrics == {str(p) for p in module.outputs(cfg, key)} | metrics | timings
        assert timings <= outs and not timings & metrics
        metric_name = Path(next(iter(metrics))).stem
        assert metric_name in (name, "anatomy_validation", "centreline_validation", f"{name}_{seq}", "metrics")
        for p in body["params"]:
            node = cfg
            for part in render(p).split("."):
                assert part in node, f"{name}: param {p} not in config"
                node = node[part]


def _catalogue_paths() -> set[str]:
    """Every path the catalogue (room_pipeline.paths / room_pipeline.catalog) builds on dvc.yaml's placeholders:
    the patient-level files of each placeholder patient, the files of the placeholder sequence (and of the
    default config's sequences), every stage's metrics and timing file."""
    from room_pipeline import catalog
    from room_pipeline.paths import EvaluationPaths, SequencePaths

    cfg = compose(conf_dir=REPO / "conf")
    out = "${output_dir}"
    found = {str(catalog.evaluation_root(out))}

    def props(obj) -> set[str]:
        return {str(getattr(obj, k)) for k, v in vars(type(obj)).items() if isinstance(v, property)}

    for patient in ("${key}", "${item.patient}", "${depth.cnn.checkpoint_patient}"):
        pp = PatientPaths(Path(out), patient)
        found |= props(pp)
        for seq in ["${item.sequence}", *cfg.sequences]:
            sp = pp.seq(seq)
            found |= props(sp) | props(pp.eval(seq)) | {str(sp.folder(m)) for m in catalog.FOLDERS}
            found |= {str(pp.sequence_record(seq, name)) for name in stages.STAGES}
            for name in stages.STAGES:
                m = pp.stage_metrics(name, seq if stages.FAN_OUT[name] == "sequences" else "")
                found |= {str(m), str(timing_path(m))}
    assert issubclass(type(pp.seq("s")), SequencePaths) and issubclass(type(pp.eval("s")), EvaluationPaths)
    return found


def test_dvc_yaml_names_only_files_the_catalogue_produces():
    """Every dataset path in dvc.yaml (deps, outs, plots, metrics under ${output_dir}) is one the catalogue
    builds; ``${depth.input}`` (a folder chosen by config) stands for each RGB source."""
    from room_pipeline import catalog

    known = _catalogue_paths()
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text(encoding="utf-8"))
    named = set()
    for st in dvc["stages"].values():
        body = st.get("do", st)
        for field in ("deps", "outs", "plots", "metrics"):
            named |= {next(iter(e)) if isinstance(e, dict) else e for e in body.get(field, [])}
    dataset = sorted(p for p in named if p.startswith("${output_dir}"))
    assert len(dataset) > 40
    unknown = [p for p in dataset if not all(p.replace("${depth.input}", s) in known for s in catalog.RGB_SOURCES)]
    assert not unknown, f"dvc.yaml names dataset paths the catalogue does not produce: {unknown}"


def _layout_names() -> set[str]:
    """File and folder names of the dataset layout that are no modality key, stage name or config key."""
    from room_pipeline import catalog

    names = set()
    for p in _catalogue_paths():
        names |= {part for part in p.split("/") if "$" not in part}
    names |= {v for k, v in vars(catalog).items() if k.isupper() and isinstance(v, str)}
    cfg = compose(conf_dir=REPO / "conf")
    keys = set(cfg) | {k for v in cfg.values() if hasattr(v, "keys") for k in v.keys()}
    return names - set(catalog.FOLDERS) - set(stages.STAGES) - keys - {"", "sequence_000"}


@pytest.mark.parametrize("script", ["write_dvc_yaml.py", "stage_deps.py"])
def test_dvc_generator_spells_no_dataset_name(script):
    """The generator builds every dataset path through the catalogue: no layout name is a literal in it."""
    import ast

    names = _layout_names()
    assert {"lung_model.obj", "render.json", "anatomy", "metadata", "surface_normals", "evaluation"} <= names
    tree = ast.parse((REPO / "scripts" / script).read_text(encoding="utf-8"))
    docs = {id(n.body[0].value) for n in ast.walk(tree)             # docstrings may name the files
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and ast.get_docstring(n) is not None}
    literals = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
                and id(n) not in docs]
    found = sorted({tok for s in literals for tok in s.replace("/", " ").split() if tok in names})
    assert not found, f"scripts/{script} spells dataset names (take them from room_pipeline.paths/catalog): {found}"


def test_dvc_generator_sees_a_spelled_name(tmp_path):
    """The check above finds a literal (a layout name written into the table by hand)."""
    names = _layout_names()
    code = 'DEPS = {"render": ["${output_dir}/${item.patient}/anatomy/lung_model.obj"]}\n'
    import ast

    literals = [n.value for n in ast.walk(ast.parse(code)) if isinstance(n, ast.Constant)]
    assert {"anatomy", "lung_model.obj"} <= {t for s in literals for t in s.replace("/", " ").split() if t in names}


def _room(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "room_pipeline.cli", *args], cwd=cwd,
                          capture_output=True, text=True)


def test_cli_params_check_ok():
    r = _room("params", "--check")
    assert r.returncode == 0, r.stderr


def test_cli_unknown_stage_and_patient_one_line_errors(tmp_path):
    r = _room("stage", "nosuchstage", "--patient", "patient_000")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "unknown stage" in r.stderr
    r = _room("stage", "segment", "--patient", "nobody", f"output_dir={tmp_path}")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "unknown patient" in r.stderr


@pytest.mark.parametrize("case", ["missing", "unreadable", "not3d", "no_air", "empty_mask"])
def test_bad_input_exits_nonzero_with_one_line_and_no_outputs(tmp_path, case):
    import nibabel as nib
    import numpy as np

    kind, path = "ct", tmp_path / "in.nii.gz"
    if case == "missing":
        path = tmp_path / "does_not_exist.nii.gz"
    elif case == "unreadable":
        path.write_bytes(b"\x00garbage")
    elif case == "not3d":
        nib.save(nib.Nifti1Image(np.zeros((8, 8), np.int16), np.eye(4)), path)
    elif case == "no_air":
        nib.save(nib.Nifti1Image(np.full((20, 20, 20), 40, np.int16), np.eye(4)), path)
    elif case == "empty_mask":
        kind = "mask"
        nib.save(nib.Nifti1Image(np.zeros((20, 20, 20), np.uint8), np.eye(4)), path)
    out = tmp_path / "out"
    r = _room("stage", "segment", "--patient", "p", f"output_dir={out}",
              f"+patients.p.kind={kind}", f"+patients.p.input={path}")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("room: error:"), r.stderr
    assert not out.exists() or not any(p.is_file() for p in out.rglob("*"))


def test_dvc_reads_yaml_with_libyaml():
    """A no-op `dvc repro` parses params.yaml once per stage and dvc.lock twice; with ruamel's pure-Python
    parser that was most of its time (benchmarks/dvc_noop.py).  ruamel.yaml.clib (declared) gives DVC's
    `typ="safe"` loads the C parser."""
    from ruamel.yaml import YAML

    assert YAML(typ="safe").Parser.__module__.startswith("ruamel.yaml.clib"), \
        "ruamel.yaml.clib is not installed: pip install ruamel.yaml.clib (pyproject.toml)"


def test_dvcignore_drops_bytecode_from_the_package_deps():
    """dvc.yaml's code deps are package folders: Python's byte-code caches inside them must not count."""
    lines = {ln.strip() for ln in (REPO / ".dvcignore").read_text(encoding="utf-8").splitlines()}
    assert {"__pycache__/", "*.pyc"} <= lines
    dvc = yaml.safe_load((REPO / "dvc.yaml").read_text())
    folders = {d for st in dvc["stages"].values() for d in st.get("do", st)["deps"]
               if d.startswith("src/") and not d.endswith(".py")}
    assert folders and all((REPO / d).is_dir() for d in folders)


def test_train_depth_waits_for_every_configured_sequence(tmp_path):
    """DVC's own graph: with `sequences` changed in params.yaml (what `dvc exp run -S sequences=[...]` writes),
    train_depth runs after the render and noise stages of every sequence of its patient, with dvc.yaml
    unchanged (its dep is the patient's sequence_index/ folder, not a copy of the list)."""
    from dvc.repo import Repo

    params = yaml.safe_load((REPO / "params.yaml").read_text(encoding="utf-8"))
    params["sequences"] = ["sequence_000", "sequence_007"]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params), encoding="utf-8")
    (tmp_path / "dvc.yaml").write_text((REPO / "dvc.yaml").read_text(encoding="utf-8"), encoding="utf-8")
    Repo.init(str(tmp_path), no_scm=True)
    graph = Repo(str(tmp_path)).index.graph
    train = next(s for s in graph if s.name == "train_depth")
    upstream = {s.name for s in graph.successors(train)}
    patient = params["depth"]["cnn"]["checkpoint_patient"]
    assert upstream >= {f"{st}@{patient}-{seq}" for st in ("render", "noise") for seq in params["sequences"]}
    assert not [d for d in train.deps if "sequence_0" in str(d)], "train_depth names a sequence: stale under -S"


def _spelled_names(path: Path, names: set[str]) -> list[str]:
    """Layout names in the string literals of the module at ``path``, docstrings and JSON keys (a dict's keys,
    a subscript: ``doc["metadata"]`` is a key of a record, not the ``metadata/`` folder) apart."""
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"))
    docs = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and ast.get_docstring(n) is not None}
    docs |= {id(k) for n in ast.walk(tree) if isinstance(n, ast.Dict) for k in n.keys if k is not None}
    docs |= {id(n.slice) for n in ast.walk(tree) if isinstance(n, ast.Subscript)}
    literals = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
                and id(n) not in docs]
    return sorted({tok for s in literals for tok in s.replace("/", " ").split() if tok in names})


def _metrics_names() -> set[str]:
    """Every metrics / timing file name (and its stem) the catalogue builds for a stage."""
    from room_pipeline.paths import PatientPaths

    p = PatientPaths(Path("/o"), "p")
    names = set()
    for stage in stages.STAGES:
        for f in (p.stage_metrics(stage, "sequence_000"), p.stage_metrics(stage),
                  p.stage_timings(stage, "sequence_000"), p.stage_timings(stage)):
            names |= {f.name, f.name.split(".")[0]}
    return names - set(stages.STAGES)


@pytest.mark.parametrize("module", sorted(p.name for p in (REPO / "src/room_pipeline/stages").glob("*.py")))
def test_stage_module_spells_no_dataset_or_metrics_name(module):
    """Stages name their files through the catalogue: no layout or metrics file name is a literal in a stage
    module, and ``write_metrics`` gets the pipeline stage's name (the catalogue builds the file name)."""
    import ast

    path = REPO / "src/room_pipeline/stages" / module
    found = _spelled_names(path, _layout_names() | _metrics_names())
    assert not found, f"stages/{module} spells dataset names (take them from room_pipeline.paths/catalog): {found}"
    for call in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(call, ast.Call) and getattr(call.func, "id", "") == "write_metrics":
            stage = call.args[1]
            assert isinstance(stage, ast.Constant) and stage.value == path.stem, \
                f"stages/{module}: write_metrics names stage {ast.unparse(stage)}, not '{path.stem}'"


def _path_like_names(path: Path, names: set[str]) -> list[str]:
    """Layout names in the path-like string literals of ``path``: a literal that is a layout name, or has no
    whitespace and a ``/``-separated part that is one (``"*/metadata/render.json"``).  Prose (literals with
    whitespace: printed Markdown, help texts), docstrings, dict keys and subscripts are apart, and so are the
    results file names a script writes (``RESULTS / "trajectory.json"``, ``res / "simulation.md"``)."""
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = {id(n.body[0].value) for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and ast.get_docstring(n) is not None}
    skip |= {id(k) for n in ast.walk(tree) if isinstance(n, ast.Dict) for k in n.keys if k is not None}
    skip |= {id(n.slice) for n in ast.walk(tree) if isinstance(n, ast.Subscript)}
    skip |= {id(n.right) for n in ast.walk(tree) if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Div)
             and ast.unparse(n.left).split(".")[-1] in ("RESULTS", "res", "results", "out_dir")}
    found = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in skip:
            s = n.value.strip()
            if s in names:
                found.add(s)
            elif s and not any(c.isspace() for c in s):
                found |= {part for part in s.split("/") if part in names}
    return sorted(found)


@pytest.mark.parametrize("script", sorted(f"{d}/{p.name}" for d in ("benchmarks", "scripts")
                                          for p in (REPO / d).glob("*.py")))
def test_benchmarks_and_scripts_find_dataset_files_through_the_catalogue(script):
    """Benchmarks and scripts build every dataset path through room_pipeline.catalog / paths: no layout name is
    a path-like literal in them (they rotted when the layout moved: issue #14)."""
    found = _path_like_names(REPO / script, _layout_names())
    assert not found, f"{script} spells dataset names (take them from room_pipeline.catalog / paths): {found}"


def test_path_like_check_sees_a_spelled_name(tmp_path):
    """The check above finds a layout name joined by hand, in a glob pattern, and ignores prose and results."""
    f = tmp_path / "x.py"
    f.write_text('a = run / "anatomy" / "lung_model.obj"\nb = d.glob("*/sequence_*/metadata/render.json")\n'
                 'print("the mesh stage makes collision_model.obj")\nRESULTS / "trajectory.json"\n', encoding="utf-8")
    assert _path_like_names(f, _layout_names()) == ["anatomy", "lung_model.obj", "metadata", "render.json"]


def test_stage_name_check_sees_a_spelled_metrics_name(tmp_path):
    """The check above finds a metrics file name written by hand."""
    f = tmp_path / "x.py"
    f.write_text('write_metrics(paths, "anatomy_validation", m)\nq = f"render_{s}.json"\n', encoding="utf-8")
    assert "anatomy_validation" in _spelled_names(f, _metrics_names())


def test_cli_run_only_functions_exist_and_stage_never_calls_them():
    """stage_deps leaves the bodies of CLI_RUN_ONLY out of a stage's code: they must be cli functions, and
    neither ``cmd_stage`` nor ``main`` may name them (a stage would then run code dvc.yaml does not list)."""
    import ast

    tree = ast.parse((REPO / "src/room_pipeline/cli.py").read_text(encoding="utf-8"))
    funcs = {f.name: f for f in tree.body if isinstance(f, ast.FunctionDef)}
    assert stage_deps.CLI_RUN_ONLY <= set(funcs)
    for caller in ("cmd_stage", "main", "stage_output_paths", "_config", "_validate"):
        names = {n.id for n in ast.walk(funcs[caller]) if isinstance(n, ast.Name)}
        assert not names & stage_deps.CLI_RUN_ONLY, caller


@pytest.mark.parametrize("args, message", [
    ([], "usage: "),
    (["/nonexistent_run", "A", "HEAD", "/nonexistent_scratch"], "no data/output"),
    (["RUN", "A", "no_such_revision_xyz", "/nonexistent_scratch"], "unknown revision"),
])
def test_compare_default_runs_bad_input_one_line_exit_2(tmp_path, args, message):
    """scripts/compare_default_runs.sh (the default run's byte-identity check) refuses bad input before it
    clones or runs anything: one line on stderr, exit 2."""
    (tmp_path / "data" / "output").mkdir(parents=True)
    args = [str(tmp_path) if a == "RUN" else a for a in args]
    r = subprocess.run(["bash", str(REPO / "scripts" / "compare_default_runs.sh"), *args], cwd=REPO,
                       capture_output=True, text=True, encoding="utf-8")
    assert r.returncode == 2 and message in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not Path("/nonexistent_scratch").exists()


def test_compare_runs_tells_a_deflate_stream_from_a_pixel_change(tmp_path):
    """scripts/compare_runs.py classifies an EXR pair: same header and pixels deflated to other bytes
    (libdeflate level 6 against 1 here) -> 'encoding'; one changed pixel -> 'different'; a file that is no EXR -> 'different'."""
    import numpy as np

    import compare_runs
    from room_pipeline.io.exr import encode_exr

    yy, xx = np.mgrid[0:40, 0:30].astype(np.float32)
    img = np.stack([yy / 40, xx / 30, (yy + xx) / 70], axis=-1)       # compressible: every chunk deflated
    changed = img.copy()
    changed[20, 10, 1] += 0.25
    sides = {"a": {"same.exr": encode_exr(img, ("B", "G", "R"), True, "pxr24", level=1),
                   "changed.exr": encode_exr(img, ("B", "G", "R"), True, "pxr24", level=1),
                   "junk.exr": b"plain bytes"},
             "b": {"same.exr": encode_exr(img, ("B", "G", "R"), True, "pxr24", level=6),
                   "changed.exr": encode_exr(changed, ("B", "G", "R"), True, "pxr24", level=1),
                   "junk.exr": b"other bytes"}}
    assert sides["a"]["same.exr"] != sides["b"]["same.exr"]
    for side, files in sides.items():
        (tmp_path / side).mkdir()
        for name, data in files.items():
            (tmp_path / side / name).write_bytes(data)
    kind, why = compare_runs.classify(tmp_path / "a", tmp_path / "b", "same.exr")
    assert kind == "encoding" and "same header and inflated pixel data" in why[0]
    assert compare_runs.classify(tmp_path / "a", tmp_path / "b", "changed.exr")[0] == "different"
    assert compare_runs.classify(tmp_path / "a", tmp_path / "b", "junk.exr")[0] == "different"


def test_compare_runs_frames_bad_input_one_line_exit_2(tmp_path):
    """scripts/compare_runs.py frames (a re-rendered sequence against a finished run's) refuses a folder that is
    no rendered sequence: one line on stderr, exit 2."""
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "compare_runs.py"), "frames", str(tmp_path),
                        str(tmp_path / "nope"), "--name", "never_written"], capture_output=True, text=True,
                       encoding="utf-8")
    assert r.returncode == 2 and "not a rendered sequence" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (REPO / "benchmarks" / "results" / "never_written.md").exists()


def test_compare_test_durations_counts_only_tests_passed_in_both(tmp_path):
    """scripts/compare_test_durations.py: the suite's speed from two JUnit files, over the tests passed in both;
    a file that is no JUnit XML, or no test in common, is one line and exit 2."""
    def junit(path, cases):
        body = "".join(f'<testcase classname="tests.t" name="{n}" time="{s}">{extra}</testcase>'
                       for n, s, extra in cases)
        path.write_text(f'<?xml version="1.0"?><testsuites><testsuite>{body}</testsuite></testsuites>',
                        encoding="utf-8")
        return path

    a = junit(tmp_path / "a.xml", [("x", 1.0, ""), ("y", 2.0, ""), ("gone", 5.0, ""), ("f", 1.0, "<failure/>")])
    b = junit(tmp_path / "b.xml", [("x", 1.5, ""), ("y", 2.0, ""), ("new", 9.0, ""), ("f", 1.0, "")])
    script = str(REPO / "scripts" / "compare_test_durations.py")
    r = subprocess.run([sys.executable, script, str(a), str(b)], capture_output=True, text=True, encoding="utf-8")
    assert r.returncode == 0, r.stderr
    assert "tests passed in both: 2" in r.stdout and "A 3.0, B 3.5, B / A 1.167" in r.stdout
    assert "median per-test B / A over 2 tests" in r.stdout and "1.250" in r.stdout
    # --write-ids: the common tests as pytest node ids (the module found under --root), for `pytest @FILE`
    ids = tmp_path / "ids.txt"
    r = subprocess.run([sys.executable, script, str(a), str(b), "--write-ids", str(ids), "--root", str(tmp_path)],
                       capture_output=True, text=True, encoding="utf-8")
    assert r.returncode == 2 and r.stderr.startswith("room: error: no test file") and not ids.exists()
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "t.py").write_text("", encoding="utf-8")
    r = subprocess.run([sys.executable, script, str(a), str(b), "--write-ids", str(ids), "--root", str(tmp_path)],
                       capture_output=True, text=True, encoding="utf-8")
    assert r.returncode == 0, r.stderr
    assert ids.read_text(encoding="utf-8") == "tests/t.py::x\ntests/t.py::y\n"
    (tmp_path / "junk.xml").write_text("not xml", encoding="utf-8")
    for args in ([str(tmp_path / "junk.xml"), str(b)],
                 [str(junit(tmp_path / "c.xml", [("z", 1.0, "")])), str(b)]):
        r = subprocess.run([sys.executable, script, *args], capture_output=True, text=True, encoding="utf-8")
        assert r.returncode == 2 and r.stderr.startswith("room: error:") and len(r.stderr.strip().splitlines()) == 1
