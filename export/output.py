"""The files `safemove export` writes: checked before the export runs, written atomically after.

An export takes tens of seconds (a simulated run for the recorded observations, parity, latency),
so a path it cannot write is refused first, not after all that work. The write itself can still
fail (a full disk): each file goes to a temporary file in the same directory, is flushed to disk
and only then renamed over the target, so a failed write leaves the old file (or none) and never
a truncated model. Imports no torch, so the CLI can check before loading it.
"""

from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path

from runtime.errors import UserError


class OutputError(UserError):
    """An output path that cannot be written (one line, exit 2)."""


def int8_path(output: Path) -> Path:
    """Where `--int8` writes its copy: next to the output, `NAME.int8.onnx`."""
    return output.with_name(output.stem + ".int8.onnx")


def check_output(output: Path, checkpoint: Path, int8: bool) -> None:
    """Refuse, naming the path, what a later write would fail on or what it would destroy: the
    output and, with --int8, its int8 copy."""
    for path in (output, int8_path(output)) if int8 else (output,):
        _check_one(path, checkpoint)


def _check_one(path: Path, checkpoint: Path) -> None:
    target = Path(os.path.realpath(path))  # a symlink is written through, not replaced
    if target.is_dir():
        raise OutputError(f"{path}: is a directory, not a file name for the ONNX model")
    if target.exists():
        if not stat.S_ISREG(target.stat().st_mode):
            raise OutputError(f"{path}: exists and is not a regular file (a device, pipe or"
                              " socket); give a file name in a writable directory")
        if checkpoint.exists() and os.path.samefile(target, checkpoint):
            raise OutputError(f"{path}: is the checkpoint itself; writing would destroy it")
    parent = target.parent
    if not parent.is_dir():
        what = "is not a directory" if parent.exists() else "does not exist"
        raise OutputError(f"{path}: the directory {parent} {what}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: the directory {parent} is not writable")


def write_atomically(files: dict[Path, bytes]) -> None:
    """Write every file or none: all are staged (written and fsynced) before any is renamed; the
    renames, in the directory just written to, need no space."""
    staged: list[tuple[Path, Path]] = []
    for path, data in files.items():
        target = Path(os.path.realpath(path))
        tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
        try:
            # 0o666 less the umask, as a plain open() would create it
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            staged.append((tmp, target))
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            for written, _ in staged:
                written.unlink(missing_ok=True)
            raise OutputError(f"{path}: writing it failed ({exc.strerror or exc}); nothing was"
                              " written") from None
    for tmp, target in staged:
        os.replace(tmp, target)
