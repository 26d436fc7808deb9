"""Shared fixtures: the base emulator process and the real `safemove` CLI as a child process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tty
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from sim_stub.emulator_process import EmulatorProcess

# --- markers by file -----------------------------------------------------------------------------

# Deterministic lock-stepped simulation: episodes of sim_stub.lockstep (through sim_stub.evaluate
# or sim_stub.train.env, in this process or in a `safemove eval` / `safemove train` child) on simulated
# time, no wall clock and no real-time peer process. The HIL files are tests/test_hil_*.py.
SIM_FILES = frozenset({"test_evaluate.py", "test_surround_people.py", "test_train.py"})


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects by marker
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """`hil` on every test in tests/test_hil_*.py, `sim` on those in SIM_FILES, so that
    `pytest -m "not hil and not sim"` runs the unit tests alone."""
    for item in items:
        name = item.path.name
        if name.startswith("test_hil_"):
            item.add_marker(pytest.mark.hil)
        elif name in SIM_FILES:
            item.add_marker(pytest.mark.sim)


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """A raw pty: the test reads and writes its master (non-blocking); the code under test
    opens the slave by its path."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


@pytest.fixture
def emulator(request: pytest.FixtureRequest) -> Iterator[EmulatorProcess]:
    """A base emulator; pass its args with @pytest.mark.parametrize('emulator', [[...]], indirect=True)."""
    args = getattr(request, "param", None) or []
    emu = EmulatorProcess(args)
    try:
        yield emu
    finally:
        emu.close()


class SafemoveProcess:
    """The real `safemove` CLI in a child process (same interpreter), stdout/stderr captured."""

    def __init__(self, args: list[str], env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "runtime.cli.main", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        self.stdout = ""
        self.stderr = ""

    def signal(self, sig: signal.Signals) -> None:
        self.proc.send_signal(sig)

    def wait(self, timeout: float) -> int:
        try:
            self.stdout, self.stderr = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.stdout, self.stderr = self.proc.communicate()
            raise AssertionError(f"safemove did not exit within {timeout} s:\n{self.stderr[-3000:]}")
        return self.proc.returncode

    def report(self) -> dict:
        lines = [ln for ln in self.stdout.splitlines() if ln.strip()]
        assert lines, f"no output; stderr:\n{self.stderr[-3000:]}"
        return json.loads(lines[-1])

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


@pytest.fixture
def safemove() -> Iterator[type[SafemoveProcess]]:
    started: list[SafemoveProcess] = []

    class Tracked(SafemoveProcess):
        def __init__(self, *a, **kw) -> None:
            super().__init__(*a, **kw)
            started.append(self)

    yield Tracked
    for p in started:
        p.kill()


@pytest.fixture
def sim(request: pytest.FixtureRequest) -> Iterator[EmulatorProcess]:
    """`safemove sim` (world + base pty + depth socket); args via indirect parametrize."""
    args = getattr(request, "param", None) or ["paper_a"]
    proc = EmulatorProcess(args, module="sim_stub.sim_server")
    try:
        yield proc
    finally:
        proc.close()


# --- the fault-injection table (`pytest -m faults`) ----------------------------------------------

FAULT_COLUMNS = ("fault", "expected", "observed", "to DEGRADED", "to zero command",
                 "to standstill", "travelled")
_fault_rows: list[tuple[str, ...]] = []


@pytest.fixture
def fault_table() -> Callable[..., None]:
    """Add a row (one cell per FAULT_COLUMNS) to the table printed after the run."""

    def add(*cells: str) -> None:
        assert len(cells) == len(FAULT_COLUMNS), cells
        _fault_rows.append(tuple(cells))

    return add


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if not _fault_rows:
        return
    rows = [FAULT_COLUMNS, *_fault_rows]
    widths = [max(len(r[i]) for r in rows) for i in range(len(FAULT_COLUMNS))]
    terminalreporter.section("fault injection: observed behaviour (times from the fault's start)")
    for k, row in enumerate(rows):
        terminalreporter.write_line(" | ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())
        if k == 0:
            terminalreporter.write_line("-+-".join("-" * w for w in widths))
