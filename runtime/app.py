"""Wiring for one run: open the base link, run the loop with a job, always leave the base stopped.

The one place that turns signals into a loop stop, and that guarantees the stop frame on every
way out (job done, SIGTERM/SIGINT, fault, exception).
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from contextlib import contextmanager

from drivers.spark_link import SparkBaseLink
from runtime.config import DEFAULT_CALIBRATION_PATH, LoadedConfig
from runtime.loop import ControlLoop, Job, LoopReport
from runtime.sdnotify import SystemdNotifier

log = logging.getLogger("safemove")


@contextmanager
def _stop_on_signals(loop: ControlLoop) -> Iterator[None]:
    def handler(signum: int, _frame: object) -> None:
        loop.request_stop(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def run_job(loaded: LoadedConfig, job: Job, max_cycles: int | None = None) -> tuple[LoopReport, dict]:
    """Run `job` on the configured base until it ends; returns the loop report and link stats."""
    if loaded.calibration_path == DEFAULT_CALIBRATION_PATH:
        log.warning("using the vendor default calibration %s: calibrate this robot",
                    loaded.calibration_path)
    link = SparkBaseLink(loaded.config.base, loaded.calibration.odometry)
    notifier = SystemdNotifier.from_environ()
    loop = ControlLoop(loaded.config, loaded.calibration, link, job, notifier, max_cycles=max_cycles)
    with _stop_on_signals(loop):
        link.open()
        try:
            report = loop.run()
        finally:
            link.close()
    stats = link.stats()
    log.info("base link: %s", stats)
    return report, stats.__dict__
