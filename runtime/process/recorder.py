"""The flight recorder: every control cycle to MCAP files, written by its own thread.

The cycle only hands over references (`offer`: a deque append, or a count when the queue is
full); serialising (runtime.process.flight_messages), compressing and writing happen in the
writer thread. Files are `safemove-<UTC time>.mcap` in the recording directory, rotated by
size and age, and when the directory's recordings would pass the total budget: the oldest
are deleted first (a ring of files). A write error (a full disk, a file size limit, a vanished
directory) stops the recording with one log line; the robot never waits and never stops for it.
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from runtime.config.calibration import CameraMount
from runtime.config.settings import LoadedConfig, RecorderConfig
from runtime.process.cycle_record import CycleRecord

log = logging.getLogger("safemove.recorder")


def recording_metadata(loaded: LoadedConfig, job: Any, **extra: str) -> dict[str, str]:
    """What a reader (and a replay) needs to know about the run: the config and calibration
    as they were, the job and its starting report (its goal, its actor file)."""
    import json
    import socket

    from runtime.config.settings import render_calibration, render_config

    return {"config_file": str(loaded.config_path),
            "calibration_file": str(loaded.calibration_path),
            "job": job.name, "host": socket.gethostname(),
            "config": render_config(loaded.config),
            "calibration": render_calibration(loaded.calibration),
            "job_summary": json.dumps(job.summary(), default=str), **extra}


def recording_directory(cfg: RecorderConfig) -> Path | None:
    """recorder.directory, else the recordings folder of systemd's LogsDirectory, else None."""
    if cfg.directory:
        return Path(cfg.directory).expanduser()
    logs = os.environ.get("LOGS_DIRECTORY", "").split(":")[0]
    return Path(logs) / "recordings" if logs else None


class Recorder:
    """Hand-off (`offer`, from the cycle) and writer thread; `stop()` drains and closes."""

    def __init__(self, directory: Path, cfg: RecorderConfig, mount: CameraMount,
                 decimation: int, metadata: dict[str, str],
                 clock: Callable[[], float] = time.monotonic, *, prefix: str = "safemove",
                 block: bool = False) -> None:
        """`prefix`: the files' names begin with it; `block`: `offer` waits for room instead
        of dropping (a lock-stepped episode, which has no deadline to keep)."""
        self.directory = directory
        self._prefix = prefix
        self._block = block
        self._cfg = cfg
        self._mount = mount
        self._decimation = decimation
        self._metadata = metadata
        self._clock = clock
        self._queue: deque[tuple[int, CycleRecord]] = deque()  # (its number in the run, it)
        self._offered = 0  # cycles offered, recorded or not: a gap in the numbers is a drop
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stopped_reason: str | None = None  # why recording stopped early (None: it did not)
        self.counts = {"cycles": 0, "dropped": 0, "files": 0, "deleted": 0, "bytes": 0}
        self._frames_read = 0
        self._writer: Any = None
        self._file: IO[bytes] | None = None
        self._path: Path | None = None
        self._opened_at = 0.0
        self._channels: dict[str, int] = {}
        self._others = 0  # bytes of the other recordings in the directory
        self.files: list[Path] = []

    # --- the cycle's side ---------------------------------------------------------------------

    def offer(self, record: CycleRecord) -> None:
        """Never blocks (unless made to): a full queue, or a recording that stopped, drops the
        cycle (counted)."""
        while (self._block and self.stopped_reason is None and self._thread is not None
               and self._thread.is_alive() and len(self._queue) >= self._cfg.queue_cycles):
            time.sleep(0.001)
        seq = self._offered
        self._offered += 1
        if self.stopped_reason is not None or len(self._queue) >= self._cfg.queue_cycles:
            self.counts["dropped"] += 1
            return
        self._queue.append((seq, record))
        self._wake.set()

    # --- life cycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Create the directory (a failure is the user's: one line, exit 2) and the thread.
        Writability is probed with an unnamed file: recorders starting together in one
        directory (`eval --jobs N --record`) must not remove each other's probe."""
        from runtime.errors import ConfigError

        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=self.directory) as probe:
                probe.write(b"\0")
        except OSError as exc:
            raise ConfigError(f"recorder.directory {self.directory}: cannot write there:"
                              f" {exc.strerror or exc}") from None
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        log.info("recording every cycle to %s", self.directory)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Write what is queued (up to `timeout_s`), close the file."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self._thread is not None and self._thread.is_alive():
            log.warning("recorder: %d cycles not written before the run ended",
                        len(self._queue))

    # --- the writer thread --------------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                self._wake.wait(0.5)
                self._wake.clear()
                while self._queue and self.stopped_reason is None:
                    self._write(*self._queue.popleft())
                if self._stop.is_set() and not self._queue:
                    break
                if self.stopped_reason is not None:
                    self._queue.clear()
                    if self._stop.is_set():
                        break
        except Exception as exc:  # a bug must not stop the robot: recording ends, loudly
            log.exception("recorder failed")
            self.stopped_reason = f"{type(exc).__name__}: {exc}"
        try:
            self._close_file()  # the last chunk is written here
        except OSError as exc:
            self._give_up(f"write error: {exc.strerror or exc}")

    def _write(self, seq: int, rec: CycleRecord) -> None:
        from runtime.process.flight_messages import cycle_messages

        try:
            now = self._clock()
            if self._writer is not None and (
                    self._file_size() > self._cfg.file_max_mb * 1e6
                    or self._file_size() + self._others > self._cfg.total_max_mb * 1e6
                    or now - self._opened_at > self._cfg.file_max_s):
                self._close_file()
            if self._writer is None:
                self._open_file(rec.t)
            full = False
            if rec.perceived is not None:
                full = self._frames_read % self._cfg.full_depth_every == 0
                self._frames_read += 1
            stamp = int(rec.t * 1e9)
            for topic, message in cycle_messages(rec, seq, full, self._decimation):
                data = message if isinstance(message, bytes) else message.SerializeToString()
                self._writer.add_message(self._channels[topic], stamp, data, stamp)
                time.sleep(0)  # hand the GIL to the control cycle if it is waiting for it
            self.counts["cycles"] += 1
        except OSError as exc:
            self._give_up(f"write error: {exc.strerror or exc}")

    def _give_up(self, why: str) -> None:
        self.stopped_reason = why
        log.error("recording stopped (the robot goes on): %s; %d cycles recorded in %s",
                  why, self.counts["cycles"], self.directory)
        try:
            self._close_file()
        except OSError:  # the same disk: the file ends without its summary (readers cope)
            pass

    def _file_size(self) -> int:
        return self._file.tell() if self._file is not None else 0

    def _open_file(self, t: float) -> None:
        from mcap.writer import CompressionType, Writer

        self._make_room()
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = self.directory / f"{self._prefix}-{stamp}-{self.counts['files']:04d}.mcap"
        self._file = open(path, "wb")  # noqa: SIM115 (closed in _close_file)
        self._path = path
        writer = Writer(self._file, compression=CompressionType.LZ4)
        writer.start(profile="", library="safemove")
        self._channels = self._register(writer)
        writer.add_metadata("safemove", self._metadata)
        from runtime.process.flight_messages import camera_transform

        stamp_ns = int(t * 1e9)
        writer.add_message(self._channels["/tf_static"], stamp_ns,
                           camera_transform(self._mount, t).SerializeToString(), stamp_ns)
        self._writer = writer
        self._opened_at = self._clock()
        self.counts["files"] += 1
        self.files.append(path)

    def _register(self, writer: Any) -> dict[str, int]:
        import json

        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
        from mcap_protobuf.schema import build_file_descriptor_set

        from runtime.process.flight_messages import CYCLE_SCHEMA

        schemas: dict[str, int] = {}
        for cls in (FrameTransform, RawImage, PointCloud, SceneUpdate):
            name = cls.DESCRIPTOR.full_name
            schemas[name] = writer.register_schema(
                name, "protobuf", build_file_descriptor_set(cls).SerializeToString())
        cycle = writer.register_schema("safemove.Cycle", "jsonschema",
                                       json.dumps(CYCLE_SCHEMA).encode())
        topics = {"/tf": "foxglove.FrameTransform", "/tf_static": "foxglove.FrameTransform",
                  "/camera/depth": "foxglove.RawImage",
                  "/camera/depth_decimated": "foxglove.RawImage",
                  "/obstacles": "foxglove.PointCloud", "/planning": "foxglove.SceneUpdate"}
        channels = {topic: writer.register_channel(topic, "protobuf", schemas[name])
                    for topic, name in topics.items()}
        channels["/cycle"] = writer.register_channel("/cycle", "json", cycle)
        return channels

    def _close_file(self) -> None:
        """Finish the file (its summary and index); the file is closed even if that fails."""
        writer, f = self._writer, self._file
        self._writer = self._file = None
        try:
            if writer is not None:
                writer.finish()
        finally:
            if f is not None:
                self.counts["bytes"] += f.tell()
                f.close()

    def _make_room(self) -> None:
        """Delete the oldest recordings until a new file of the budget's share fits."""
        budget = self._cfg.total_max_mb * 1e6
        room = min(self._cfg.file_max_mb * 1e6, 0.5 * budget)
        old = sorted(self.directory.glob(f"{self._prefix}-*.mcap"),
                     key=lambda p: (p.stat().st_mtime, p.name))
        used = sum(p.stat().st_size for p in old)
        while old and used + room > budget:
            oldest = old.pop(0)
            used -= oldest.stat().st_size
            oldest.unlink()
            self.counts["deleted"] += 1
            log.info("recorder: deleted %s to stay under recorder.total_max_mb", oldest.name)
        self._others = used

    def summary(self) -> dict[str, Any]:
        return {"directory": str(self.directory), **self.counts,
                "stopped": self.stopped_reason, "files_kept": [p.name for p in self.files
                                                               if p.exists()]}
