"""Every signal that ends the runtime stops the base first, through the real `safemove drive`
process against the base emulator: TERM and INT are stop requests (exit 0); HUP, QUIT, USR1,
USR2 and ABRT (what systemd's watchdog sends) end the process by the same signal once the stop
frame is out, so systemd sees what happened. The emulated firmware's watchdog is off: only the
runtime's stop frame can stop these wheels."""

from __future__ import annotations

import signal

import pytest
from fault_run import figures, sample, wait_moving, watch

pytestmark = [pytest.mark.hil, pytest.mark.faults]

SIGNALS = [signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1,
           signal.SIGUSR2, signal.SIGABRT]


@pytest.mark.parametrize("emulator", [["--watchdog-s", "0"]], indirect=True)
@pytest.mark.parametrize("sig", SIGNALS, ids=[s.name for s in SIGNALS])
def test_signal_sends_the_stop_frame_before_the_process_ends(emulator, safemove, fault_table, sig):
    run = safemove(["drive", "--set", f"base.port={emulator.link}",
                    "--set", "loop.stats_interval_s=0", "--twist", "0.2", "0",
                    "--duration", "60"])
    start = wait_moving(emulator, 0.19)
    t0 = sample(emulator).t
    run.signal(sig)
    stop = emulator.wait_for("command", timeout_s=5, left=0, right=0)
    samples = watch(emulator, 1.0)
    code = run.wait(timeout=10)
    assert stop["t"] >= t0
    assert samples[-1].v == 0.0  # the wheels stopped and stay stopped: nothing else sent
    assert "Traceback" not in run.stderr
    assert f"{sig.name} received: stopping the base" in run.stderr
    report = run.report()  # the run's report is written before the process ends
    assert report["state"] == "STOPPED" and report["reason"] == sig.name
    if sig in (signal.SIGTERM, signal.SIGINT):
        assert code == 0
        observed = "stop frame, exit 0"
    else:
        assert code == -sig, f"exit {code}: the process must end by {sig.name}"
        observed = f"stop frame, then ended by {sig.name}"
    if sig is signal.SIGABRT:  # the watchdog's signal: every thread's stack for the journal
        assert "Most recent call first" in run.stderr or "most recent call first" in run.stderr
    fig = figures(t0, start, samples, {"transitions": []}, emulator.history)
    fault_table(sig.name, "stop frame, then exit", observed, *fig.cells())
