"""The ``room`` command line.

    room stage NAME --patient ID[/SEQUENCE] [--params params.yaml] [key=value ...]
        Run one pipeline stage for one patient (per-sequence stages such as
        `trajectory` take PATIENT/SEQUENCE; what dvc.yaml calls).  The
        config is the composition of conf/ with the Hydra overrides given, or,
        with --params, that composed file plus dot-list overrides.
    room run [-m] [--patient ID] [--until STAGE] [hydra overrides ...]
        Run the stages in order for one patient into output_dir, each in its
        own process (as DVC does), stopping after --until; then write
        <output_dir>/manifest.json.  -m/--multirun: a Hydra multirun, one
        run per point of the sweep (key=a,b, hydra/launcher=...).
    room params [--check] [hydra overrides ...]
        Write params.yaml as the composition of conf/ (what `dvc exp run`
        does); --check only reports whether params.yaml is up to date.
    room calibrate-noise --frames DIR --out PROFILE.npz [key=value ...]
        Measure a sensor-noise profile from real endoscope frames
        (room_pipeline.noise.cli).
    room export --format {colmap,nerfstudio,tum,ply} SEQ OUT [--overwrite] [--images rgb|rgb_noisy|none]
                [--depth png16|npy|none] [--point-stride N]
        Export a rendered sequence with its ground-truth poses (room_pipeline.export).
    room report [--output-dir DIR] [--out FILE] [--max-frames N] [overrides]
        Write the self-contained HTML report of a dataset (room_pipeline.report).
    room realism --real DIR [--synth DIR] [--json OUT]
        Realism statistics of rendered frames against real ones (room_pipeline.realism).
    room navigate {demo,episode,targets} ...
        Vision-based navigation: the paper's planning demonstration, closed-loop episodes (room_pipeline.navigation).
    `room TOOL --help` lists a tool's options.

Bad input ends with one line on stderr ("room: error: ...") and exit status 2.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from .errors import ConfigError, RoomError


def _config(args: argparse.Namespace):
    from .config.compose import compose, load_params

    if getattr(args, "params", None):
        return load_params(args.params, args.overrides)
    return compose(args.overrides)


def _validate(cfg, stage: str | None = None, key: str | None = None) -> None:
    """The whole composed config (and a stage's --patient), checked before any work."""
    from . import stages
    from .config.validate import validate_config, validate_key

    if stage is not None and key is not None:
        validate_key(cfg, stage, key, stages.FAN_OUT[stage])
    validate_config(cfg)


def stage_output_paths(cfg, name: str, key: str) -> list[Path]:
    """What stage ``name`` writes for ``key``: its declared outputs, its metrics file and timing file."""
    from . import stages
    from .paths import PatientPaths

    from .io.metrics import timing_path

    outs = [Path(p) for p in stages.load(name).outputs(cfg, key)]
    if stages.FAN_OUT[name] != "dataset":
        patient, _, sequence = key.partition("/")
        metrics = PatientPaths(Path(cfg.output_dir), patient).stage_metrics(name, sequence)
    else:   # the dataset stage (tables) lists its metrics file, the last of its outputs
        metrics = outs[-1]
    return [p for p in outs if p != metrics] + [metrics, timing_path(metrics)]


def stage_blas_limit():
    """The BLAS thread pools of a stage process, limited to ``ROOM_BLAS_THREADS`` threads (default 1; 0 = the
    libraries' own default).  A stage's numpy work is skinny products ((N, 3) by (3, 3), matrix-vector) and
    long dot products, which OpenBLAS splits over threads whose spin-waits cost more CPU than they save:
    ``validate_anatomy`` on the phantom took 93 s wall, 68 s user + 51 s system CPU with OpenBLAS's two
    threads and 76-91 s, 58-62 + 18-28 s with one (session 16, this machine, repeated runs; README, Pitfalls).
    One thread also
    makes a long dot product's rounding independent of the core count.  Workers of the executor set their
    own limits (:func:`room_pipeline.execution.executor_base.limit_threads`)."""
    import contextlib

    raw = os.environ.get("ROOM_BLAS_THREADS", "1").strip() or "1"
    if not raw.isdigit():
        raise ConfigError(f"ROOM_BLAS_THREADS must be a whole number of threads (0 = the libraries' default), "
                          f"got {raw!r}")
    n = int(raw)
    if n <= 0:
        return contextlib.nullcontext()
    if "numpy" not in sys.modules:     # a fresh `room` process: its BLAS, loaded by the stage's imports, reads these
        os.environ["OPENBLAS_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(n)

    @contextlib.contextmanager
    def limited():                     # applied and undone around the stage's run only (an in-process caller keeps
        from threadpoolctl import threadpool_limits   # its own settings, also when the stage fails)

        with threadpool_limits(limits=n, user_api="blas"):
            yield

    return limited()


def cmd_stage(args: argparse.Namespace) -> int:
    from . import stages
    from .catalog import MANIFEST_NAME
    from .io.outputs import stage_outputs

    blas = stage_blas_limit()                      # before the stage's imports load numpy's BLAS
    module = stages.load(args.name)
    cfg = _config(args)
    _validate(cfg, args.name, args.patient)
    manifest = Path(cfg.output_dir) / MANIFEST_NAME
    with stage_outputs(stage_output_paths(cfg, args.name, args.patient), manifest=manifest), blas:
        metrics = module.run(cfg, args.patient)
    if not args.quiet:
        summary = ", ".join(f"{k}={v}" for k, v in metrics.items() if not isinstance(v, dict))
        print(f"[{args.name}] {args.patient}: {summary}")
    return 0


#: seconds `room run` gives an interrupted stage to clean up before it is killed
STAGE_GRACE_S = 30.0


def _run_stage_process(cmd: list[str]) -> int:
    """Run one stage process; on SIGINT/SIGTERM forward the signal, give it STAGE_GRACE_S to clean up, then kill.

    Returns the stage's exit status; an interruption re-raises (KeyboardInterrupt or Terminated) after the
    stage has exited.
    """
    import signal

    from .io.outputs import Terminated

    proc = subprocess.Popen(cmd)

    def on_term(signum, frame):
        raise Terminated(signum)

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        return proc.wait()
    except (KeyboardInterrupt, Terminated) as exc:
        sig = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            if proc.poll() is None:
                proc.send_signal(sig)        # a terminal's Ctrl-C reached it already; a `kill -INT` did not
            proc.wait(timeout=STAGE_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        except KeyboardInterrupt:            # a second Ctrl-C: stop waiting
            proc.kill()
            proc.wait()
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_pipeline(cfg, patient: str | None = None, until: str | None = None) -> int:
    """Run the stages in order for one patient with the composed config ``cfg``; 0 or the failed stage's exit status.

    The whole config is validated first (one error line, before any stage).  Each stage runs in its own
    process from ``<output_dir>/<patient>/run_config.yaml`` (as DVC runs them from params.yaml).  The patient
    is ``patient``, else the config's ``patient`` key (``+patient=ID``, e.g. swept by ``room run -m``), else the
    first configured.  Any ``manifest.json`` of an earlier run is removed first and temporary files a killed
    run left are removed; after the last stage, ``<output_dir>/manifest.json`` lists every file under
    output_dir with its sha256, the resolved config and the library versions.  A stage that fails prints its
    own one-line reason; `room run` adds no second line for it.

    Why a runner beside DVC: Hydra multirun sweeps (`room run -m noise.beta=0.2,0.5`) compose one config per
    job and run it in its own output folder, which `dvc exp run` does not do without a workspace per job; and a
    run needs no git/DVC repository.  It runs the same :data:`room_pipeline.stages.STAGES` table, each stage
    through `room stage` as dvc.yaml does, so the two give the same bytes (tests/test_pipeline_e2e.py).
    """
    from omegaconf import OmegaConf

    from . import stages
    from .catalog import MANIFEST_NAME
    from .config.compose import patient_entry
    from .io.atomic import write_text
    from .execution.manifest import write_manifest
    from .io.outputs import remove_outputs, remove_temp_files


    patients = list(cfg.get("patients") or {})
    if not patients:
        raise RoomError("no patients configured")
    patient = patient or cfg.get("patient") or patients[0]
    patient_entry(cfg, patient)  # validates
    _validate(cfg)
    is_phantom = patient in (cfg.get("phantoms") or {})
    trains = patient == str(OmegaConf.select(cfg, "depth.cnn.checkpoint_patient", default=""))
    order = [s for s in stages.STAGES if (is_phantom or stages.FAN_OUT[s] != "phantoms")
             and (trains or stages.FAN_OUT[s] != "training")]
    if until:
        if until not in order:
            raise RoomError(f"--until {until}: not a stage of this run ({', '.join(order)})")
        order = order[: order.index(until) + 1]
    output_dir = Path(cfg.output_dir)
    run_dir = output_dir / patient
    remove_outputs([output_dir / MANIFEST_NAME])
    if output_dir.is_dir():
        remove_temp_files([output_dir])      # leftovers of a killed run (SIGKILL gives no chance to clean)
    config_path = run_dir / "run_config.yaml"
    write_text(config_path, OmegaConf.to_yaml(cfg))
    for name in order:
        fan = stages.FAN_OUT[name]
        keys = ([f"{patient}/{s}" for s in cfg.get("sequences") or []] if fan == "sequences"
                else ["all"] if fan == "dataset" else [patient])
        for key in keys:
            print(f"room run: stage {name} ({key})", flush=True)
            rc = _run_stage_process([sys.executable, "-m", "room_pipeline.cli", "stage", name,
                                     "--patient", key, "--params", str(config_path)])
            if rc != 0:
                if rc not in (2, 130, 143, -2, -15):     # the stage printed no `room: error:` line of its own
                    print(f"room: error: stage '{name}' failed for {key} (exit {rc})", file=sys.stderr)
                return rc if rc > 0 else 128 - rc
    manifest = write_manifest(output_dir, OmegaConf.to_container(cfg, resolve=True),
                              extra={"room_run": {"patient": patient, "stages": order}})
    print(f"room run: done -> {run_dir} (manifest: {manifest})")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    if args.multirun:
        return multirun(args.overrides, args.patient, args.until)
    from .config.compose import compose

    return run_pipeline(compose(args.overrides), args.patient, args.until)


def multirun(overrides: list[str], patient: str | None = None, until: str | None = None) -> int:
    """``room run -m``: a Hydra multirun of :func:`run_pipeline`, one job per point of the sweep.

    The overrides are Hydra's (``key=a,b`` sweeps, ``hydra/launcher=...``, ``hydra.sweep.dir=...``); the jobs
    run one after the other with the default launcher and the sweep stops at the first failed job (its exit
    status is returned).  Hydra writes its own records under ``hydra.sweep.dir`` (default
    ``multirun/<date>/<time>``); ``hydra.job.chdir=False`` keeps the working directory, so a relative
    ``output_dir`` means the same folder as for ``room run``.
    """
    import hydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf, open_dict

    from .config.compose import CONFIG_NAME, find_conf_dir

    conf = find_conf_dir()
    cwd = Path.cwd()

    @hydra.main(config_path=str(conf), config_name=CONFIG_NAME, version_base=None)
    def job(cfg) -> int:
        OmegaConf.resolve(cfg)
        if Path.cwd() != cwd and not Path(cfg.output_dir).is_absolute():   # a launcher that changed directory
            with open_dict(cfg):
                cfg.output_dir = str(cwd / cfg.output_dir)
        print(f"room run -m: job {HydraConfig.get().job.num}: {' '.join(HydraConfig.get().overrides.task)}",
              flush=True)
        try:
            rc = run_pipeline(cfg, patient, until)
        except RoomError as exc:
            print(f"room: error: {exc}", file=sys.stderr)
            rc = 2
        if rc:
            raise SystemExit(rc)          # not an Exception: Hydra does not catch it, the sweep stops here
        return 0

    argv = sys.argv
    sys.argv = ["room run -m", "--multirun", "hydra.job.chdir=False", "hydra.job.name=room_run", *overrides]
    try:
        job()
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.argv = argv
    return 0


def cmd_params(args: argparse.Namespace) -> int:
    from .config.compose import compose_yaml, write_params

    target = Path(args.output)
    if args.check:
        fresh = compose_yaml(args.overrides)
        current = target.read_text(encoding="utf-8") if target.exists() else ""
        if fresh != current:
            print(f"{target} is stale: run `room params` (or `dvc exp run`) to recompose it from conf/",
                  file=sys.stderr)
            return 1
        print(f"{target} is the composition of conf/")
        return 0
    write_params(target, args.overrides)
    print(f"wrote {target}")
    return 0


#: sub-commands that are tools, not pipeline steps: name -> (module with ``main(argv)``, help).  They are
#: imported by name only when called, so `room stage` (what dvc.yaml runs) never depends on their code.
TOOLS = {
    "calibrate-noise": ("room_pipeline.noise.cli", "measure a sensor-noise profile from real endoscope frames"),
    "export": ("room_pipeline.export", "export a rendered sequence (COLMAP, nerfstudio, TUM, PLY point clouds)"),
    "report": ("room_pipeline.report.cli", "write the self-contained HTML report of a dataset"),
    "realism": ("room_pipeline.realism", "image statistics of rendered frames against real bronchoscopy frames"),
    "navigate": ("room_pipeline.navigation.cli", "navigation demo (depth -> point cloud -> planner) and closed-loop episodes"),
}


def _tool(name: str):
    def call(args: argparse.Namespace) -> int:
        import importlib

        module = importlib.import_module(TOOLS[name][0])
        return int(module.main(list(args.tool_args)) or 0)

    return call


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="room", description="room-pipeline: CT -> bronchoscopy datasets")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("stage", help="run one pipeline stage for one patient")
    s.add_argument("name")
    s.add_argument("--patient", required=True)
    s.add_argument("--params", help="composed config file (params.yaml); default: compose conf/")
    s.add_argument("--quiet", action="store_true")
    s.add_argument("overrides", nargs="*", help="key=value overrides")
    s.set_defaults(func=cmd_stage)

    r = sub.add_parser("run", help="run the stages in order for one patient")
    r.add_argument("--patient", help="patient id (default: the first configured)")
    r.add_argument("--until", help="stop after this stage")
    r.add_argument("-m", "--multirun", action="store_true",
                   help="Hydra multirun: one run per point of the sweep (key=a,b ...; hydra/launcher=...)")
    r.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. phantom.spacing_mm=[1,1,1]")
    r.set_defaults(func=cmd_run)

    q = sub.add_parser("params", help="compose conf/ into params.yaml")
    q.add_argument("--check", action="store_true", help="only check that params.yaml is fresh")
    q.add_argument("--output", default="params.yaml")
    q.add_argument("overrides", nargs="*")
    q.set_defaults(func=cmd_params)

    for name, (_, text) in TOOLS.items():   # each parses its own arguments (`room NAME --help`)
        t = sub.add_parser(name, help=text, add_help=False, prefix_chars="\0")
        t.add_argument("tool_args", nargs=argparse.REMAINDER)
        t.set_defaults(func=_tool(name))
    return p


def main(argv: list[str] | None = None) -> int:
    """The `room` command: exit status 0, 2 (bad input: one line), 130 (interrupted) or 143 (terminated)."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        # Ctrl-C before _main installed its handler (the process was still parsing or importing: a terminal's
        # Ctrl-C reaches a just-started stage process too): nothing was written yet; one line, no traceback
        print("room: interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    # overrides (key=value) may come before or after the options
    args, extra = parser.parse_known_args(argv)
    bad = [e for e in extra if e.startswith("-") or "=" not in e]
    if bad:
        parser.error(f"unrecognized arguments: {' '.join(bad)}")
    args.overrides = list(getattr(args, "overrides", [])) + extra
    import contextlib
    import signal

    from .io import outputs

    outputs.RECEIVED.clear()                       # signals of an earlier in-process call do not count
    with contextlib.suppress(ValueError):          # not the main thread: leave SIGINT to Python
        signal.signal(signal.SIGINT, outputs.raise_interrupt)
    try:
        return int(args.func(args) or 0)
    except RoomError as exc:
        if not outputs.RECEIVED:
            print(f"room: error: {exc}", file=sys.stderr)
            return 2
        exc_signal = outputs.RECEIVED[0]
    except BaseException as exc:
        # an interruption, or whatever an interruption turned into where it landed (a native import's
        # ImportError, say): the stage's clean-up has run; report the signal, not a traceback
        if isinstance(exc, outputs.Terminated):
            exc_signal = signal.SIGTERM
        elif isinstance(exc, KeyboardInterrupt):
            exc_signal = signal.SIGINT
        elif outputs.RECEIVED:
            exc_signal = outputs.RECEIVED[0]
        else:
            raise
    if exc_signal == signal.SIGTERM:
        print("room: terminated", file=sys.stderr)
        return 143
    print("room: interrupted", file=sys.stderr)
    return 130


if __name__ == "__main__":
    sys.exit(main())
