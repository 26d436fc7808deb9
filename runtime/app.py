"""Wiring for one run: open the base link, run the loop with a job, always leave the base stopped.

The one place that turns signals into a loop stop, and that guarantees the stop frame on every
way out (job done, SIGTERM/SIGINT, fault, exception).
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from drivers.depth_source import DepthSource
from drivers.spark_link import SparkBaseLink
from runtime.config import DEFAULT_CALIBRATION_PATH, DepthConfig, LoadedConfig
from runtime.errors import ConfigError
from runtime.loop import ControlLoop, Job, LoopReport
from runtime.sdnotify import SystemdNotifier

log = logging.getLogger("safemove")


@contextmanager
def on_stop_signals(stop: Callable[[str], None]) -> Iterator[None]:
    """While inside, SIGTERM and SIGINT call `stop(signal name)` instead of killing the process
    (whoever runs the robot then stops the base on its way out); the old handlers come back
    after."""

    def handler(signum: int, _frame: object) -> None:
        stop(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def open_depth_source(cfg: DepthConfig, source: str) -> DepthSource | None:
    """The configured depth source, not yet started (None for `none`)."""
    if cfg.source == "none":
        return None
    if cfg.source == "sim":
        if not cfg.sim_socket:
            raise ConfigError(f"{source}: key 'depth.sim_socket': must be set when depth.source is sim")
        from drivers.sim_depth_link import SimDepthSource

        return SimDepthSource(cfg.sim_socket)
    from drivers.realsense_live import LiveD435Source

    return LiveD435Source(cfg)


def run_job(loaded: LoadedConfig, job: Job, max_cycles: int | None = None) -> tuple[LoopReport, dict]:
    """Run `job` on the configured base (and depth source) until it ends; returns the loop
    report and the drivers' counters."""
    if loaded.calibration_path == DEFAULT_CALIBRATION_PATH:
        log.warning("using the vendor default calibration %s: calibrate this robot",
                    loaded.calibration_path)
    depth = open_depth_source(loaded.config.depth, str(loaded.config_path))
    link = SparkBaseLink(loaded.config.base, loaded.calibration.odometry)
    notifier = SystemdNotifier.from_environ()
    loop = ControlLoop(loaded.config, loaded.calibration, link, job, notifier,
                       max_cycles=max_cycles, depth=depth)
    with on_stop_signals(loop.request_stop):
        link.open()
        try:
            if depth is not None:
                depth.start()
            report = loop.run()
        finally:
            link.close()
            if depth is not None:
                depth.stop()
    stats = link.stats().__dict__
    log.info("base link: %s", stats)
    if depth is not None:
        stats["depth_source"] = {**depth.counts, "digest": getattr(depth, "digest", None)}
    return report, stats
