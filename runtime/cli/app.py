"""Wiring for one run: open the base link, run the loop with a job, always leave the base stopped.

The one place that turns signals into a loop stop, and that guarantees the stop frame on every
way out (job done, a signal Python can handle, fault, exception).
"""

from __future__ import annotations

import faulthandler
import logging
import os
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from drivers.depth_source import CountedDepthSource
from drivers.spark.link import SparkBaseLink
from runtime.config.settings import DEFAULT_CALIBRATION_PATH, DepthConfig, LoadedConfig
from runtime.errors import ConfigError
from runtime.process.control_server import ControlHandoff, ControlServer
from runtime.process.loop import ControlLoop, Job, LoopReport
from runtime.process.recorder import Recorder, recording_directory, recording_metadata
from runtime.process.sdnotify import SystemdNotifier

log = logging.getLogger("safemove")


# Signals that end a run: each stops the base first. TERM and INT are requests to stop (exit 0);
# the others end the process by the same signal once the base is stopped, so systemd sees what
# happened: ABRT is what its watchdog sends (WatchdogSignal= default), HUP a closed terminal.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
FATAL_SIGNALS = (signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2, signal.SIGABRT)
_fatal: list[signal.Signals] = []


@contextmanager
def on_stop_signals(stop: Callable[[str], None]) -> Iterator[None]:
    """While inside, the stop and fatal signals call `stop(signal name)` instead of killing the
    process (whoever runs the robot then stops the base on its way out); the old handlers come
    back after. A fatal signal is re-raised by `exit_by_fatal_signal` once the run is over. For
    ABRT, every thread's stack goes to stderr at once (the journal), even if the main thread is
    stuck and never runs the handler: then the link's own command timeout stops the base."""

    def handler(signum: int, _frame: object) -> None:
        sig = signal.Signals(signum)
        if sig in FATAL_SIGNALS and not _fatal:
            _fatal.append(sig)
        log.warning("%s received: stopping the base", sig.name)
        stop(sig.name)

    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS + FATAL_SIGNALS}
    enabled_here = not faulthandler.is_enabled()
    # installed over ours: ABRT dumps the stacks to the process's own stderr, then runs `handler`
    # (sys.__stderr__ is None only if the process started without one: then, as faulthandler
    # itself does for file=None, sys.stderr)
    stderr = sys.__stderr__
    faulthandler.enable(file=stderr if stderr is not None else sys.stderr)
    try:
        yield
    finally:
        if enabled_here:
            faulthandler.disable()
        for sig, old in previous.items():
            signal.signal(sig, old)


def exit_by_fatal_signal() -> None:
    """If a fatal signal ended the run, end the process by it (default action) now that the base
    is stopped and the report written."""
    if _fatal:
        sig = _fatal[0]
        sys.stdout.flush()
        sys.stderr.flush()
        signal.signal(sig, signal.SIG_DFL)
        os.kill(os.getpid(), sig)


def open_depth_source(cfg: DepthConfig, source: str) -> CountedDepthSource | None:
    """The configured depth source, not yet started (None for `none`)."""
    if cfg.source == "none":
        return None
    if cfg.source == "sim":
        if not cfg.sim_socket:
            raise ConfigError(f"{source}: key 'depth.sim_socket': must be set when depth.source is sim")
        from drivers.sim_depth_link import SimDepthSource

        return SimDepthSource(cfg.sim_socket)
    from drivers.realsense.live import LiveD435Source

    return LiveD435Source(cfg)


def _recorder(loaded: LoadedConfig, job: Job) -> Recorder | None:
    """The flight recorder where recording is configured (recorder.directory, or systemd's
    LogsDirectory), with what a reader needs to know about the run in the files' metadata."""
    directory = recording_directory(loaded.config.recorder)
    if directory is None:
        return None
    return Recorder(directory, loaded.config.recorder, loaded.calibration.camera,
                    loaded.config.perception.decimation, recording_metadata(loaded, job))


def run_job(loaded: LoadedConfig, job: Job, max_cycles: int | None = None,
            control: tuple[Path, ControlHandoff] | None = None) -> tuple[LoopReport, dict]:
    """Run `job` on the configured base (and depth source) until it ends; returns the loop
    report and the drivers' counters. `control`: the control socket's path and the hand-off
    the job (a CommandedJob) shares with it; the socket listens before the base is opened
    (a socket that cannot listen refuses the start, exit 2) and is removed on the way out."""
    if loaded.calibration_path == DEFAULT_CALIBRATION_PATH:
        log.warning("using the vendor default calibration %s: calibrate this robot",
                    loaded.calibration_path)
    depth = open_depth_source(loaded.config.depth, str(loaded.config_path))
    link = SparkBaseLink(loaded.config.base, loaded.calibration.odometry)
    notifier = SystemdNotifier.from_environ()
    server = None
    if control is not None:
        server = ControlServer(control[0], control[1], loaded.config.limits.v_max)
    recorder = _recorder(loaded, job)
    loop = ControlLoop(loaded.config, loaded.calibration, link, job, notifier,
                       max_cycles=max_cycles, depth=depth,
                       control=None if control is None else control[1], recorder=recorder)
    with on_stop_signals(loop.request_stop):
        if recorder is not None:
            recorder.start()
        if server is not None:
            server.start()
        try:
            link.open()
            try:
                if depth is not None:
                    depth.start()
                report = loop.run()
            finally:
                link.close()
                if depth is not None:
                    depth.stop()
        finally:
            if server is not None:
                server.stop()
            if recorder is not None:
                recorder.stop()
    stats = link.stats().__dict__
    if server is not None:
        stats["control_socket"] = dict(server.counts)
    if recorder is not None:
        stats["recorder"] = recorder.summary()
    log.info("base link: %s", stats)
    if depth is not None:
        stats["depth_source"] = {**depth.counts, "digest": getattr(depth, "digest", None)}
    return report, stats
