"""``room calibrate-noise --frames DIR --out PROFILE.npz [key=value ...]``: measure a noise profile.

Writes PROFILE.npz and PROFILE.json (room_pipeline.noise.profile) from the real endoscope frames
in DIR (room_pipeline.noise.calibrate).  Settings: conf/noise/default.yaml's ``noise`` section
(the dataclass defaults outside a project); overrides name its keys (``beta=...``,
``calibration.tile=32``, or a calibration key alone: ``tile=32``, ``holdout_every=0``; a leading
``noise.`` is allowed).  Non-image files are skipped with a warning.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import RoomError


def _noise_section(overrides: list[str]) -> dict:
    """conf/noise/default.yaml (dataclass defaults outside a project) with key=value overrides applied."""
    import dataclasses

    from omegaconf import OmegaConf

    from ..config.compose import find_conf_dir
    from ..errors import ConfigError
    from .calibrate import CalibrationParams
    from .params import NoiseParams

    try:
        base = OmegaConf.load(find_conf_dir() / "noise" / "default.yaml")
    except (ConfigError, FileNotFoundError):
        base = OmegaConf.create({})
    top = {f.name for f in dataclasses.fields(NoiseParams)}
    calib = {f.name for f in dataclasses.fields(CalibrationParams)}
    dotlist = []
    for item in overrides:
        key, _, value = item.partition("=")
        key = key.removeprefix("noise.")
        if key.split(".")[0] not in top and key in calib:
            key = f"calibration.{key}"
        dotlist.append(f"{key}={value}")
    cfg = OmegaConf.merge(base, OmegaConf.from_dotlist(dotlist)) if dotlist else base
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def cmd_calibrate_noise(args: argparse.Namespace) -> int:
    import dataclasses
    import warnings

    from .calibrate import calibrate_folder
    from .params import NoiseParams

    params = NoiseParams.from_dict(_noise_section(args.overrides))
    cp = params.calibration_params()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        profile = calibrate_folder(Path(args.frames), cp)
    for w in caught:
        print(f"room: warning: {w.message}", file=sys.stderr)
    command = " ".join(["room calibrate-noise", "--frames", str(args.frames), "--out", str(args.out),
                        *args.overrides])
    prov = dict(profile.provenance, command=command,
                calibration_params=dataclasses.asdict(cp))
    profile = dataclasses.replace(profile, provenance=prov)
    npz, meta = profile.save(args.out)
    test = profile.intensity_test
    print(f"room calibrate-noise: {prov['frame_count']} frame(s), {prov['tiles']} tiles "
          f"({len(prov['split']['held_out'])} held out); noise std (levels) R,G,B = "
          + ", ".join(f"{v:.3f}" for v in profile.std)
          + f"; intensity: {test.get('decision', 'n/a')}")
    print(f"wrote {npz} and {meta}")
    return 0



def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="room calibrate-noise", description="measure a sensor-noise profile from real endoscope frames")
    p.add_argument("--frames", required=True, help="folder of real frames (JPEG/PNG/...)")
    p.add_argument("--out", required=True, help="profile to write (.npz; the .json goes next to it)")
    p.add_argument("overrides", nargs="*", help="key=value overrides of the noise section")
    args, extra = p.parse_known_args(argv)
    bad = [e for e in extra if e.startswith("-") or "=" not in e]
    if bad:
        p.error(f"unrecognized arguments: {' '.join(bad)}")
    args.overrides = list(args.overrides) + extra
    try:
        return cmd_calibrate_noise(args)
    except RoomError as exc:
        print(f"room: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
