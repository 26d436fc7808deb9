"""Writing the per-robot calibration file: validated, atomic, with a backup and a printed diff.

The new file is the schema's documented rendering (like the shipped default), checked by
loading it back through the schema before anything on disk changes, so a bad estimate (out of
range, not finite) is refused with the file untouched. The previous file is copied to a
time-stamped backup beside it, then the new one replaces it atomically (write a temporary file
in the same folder, fsync, rename): a crash leaves the old file or the new one, never half.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path

import yaml

from runtime.config.calibration import Calibration, CameraMount, OdometryCalibration
from runtime.config.schema import build, to_plain
from runtime.config.settings import DEFAULT_CALIBRATION_PATH, render_calibration
from runtime.errors import ConfigError, UserError


def rounded(cal: Calibration) -> Calibration:
    """Values rounded to what the measurements resolve (0.1 mm, 0.001 deg, 6 significant
    digits of m/tick), so the file stays readable and diffs show real changes only."""
    cam, odo = cal.camera, cal.odometry
    return Calibration(
        CameraMount(tuple(round(v, 4) for v in cam.translation_m),
                    tuple(round(v, 3) for v in cam.rpy_deg)),
        OdometryCalibration(float(f"{odo.m_per_tick:.6g}"), round(odo.axle_length_m, 4),
                            odo.left_encoder_offset),
    )


def differences(old: Calibration, new: Calibration) -> list[str]:
    """One line per changed key: `section.key: old -> new`."""
    lines = []
    for section in dataclasses.fields(Calibration):
        a, b = to_plain(getattr(old, section.name)), to_plain(getattr(new, section.name))
        for key in a:
            if a[key] != b[key]:
                lines.append(f"{section.name}.{key}: {a[key]} -> {b[key]}")
    return lines


def output_path(calibration_path: Path, output: Path | None) -> Path:
    """Where to write: --output, else the calibration file the config uses, but never the
    shipped vendor default (it belongs to the installation, not to one robot)."""
    if output is not None:
        return output
    if calibration_path.resolve() == DEFAULT_CALIBRATION_PATH.resolve():
        raise UserError(
            f"{calibration_path}: the config uses the shipped vendor calibration; give --output"
            " FILE for this robot's calibration and point the config's calibration_file at it")
    return calibration_path


def write_calibration(path: Path, new: Calibration, old: Calibration) -> tuple[Path | None,
                                                                                list[str]]:
    """Validate and write `new` to `path`; returns (backup path or None, differences)."""
    new = rounded(new)
    text = render_calibration(new)
    build(Calibration, yaml.safe_load(text), f"{path} (new calibration)")  # ConfigError if bad
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ConfigError(f"{path}: folder {folder} does not exist")
    backup = None
    try:
        if path.exists():
            stamp = time.strftime("%Y%m%d-%H%M%S")
            backup = path.with_name(f"{path.name}.{stamp}.bak")
            n = 1
            while backup.exists():  # two calibrations within a second keep both backups
                backup, n = path.with_name(f"{path.name}.{stamp}-{n}.bak"), n + 1
            shutil.copy2(path, backup)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the calibration file: {exc.strerror}") from None
    return backup, differences(old, new)
