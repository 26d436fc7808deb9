"""Start and talk to the base emulator as a separate process (HIL tests, demo, benchmarks).

The emulator speaks JSON lines: the first stdout line announces the pty; stdin takes control ops
({"op": "truth"}, ...); stdout carries events. A reader thread queues events so callers can wait
for one with a deadline.
"""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any


class EmulatorProcess:
    """`with EmulatorProcess(["--watchdog-s", "0.5"]) as emu: ... emu.link ...`

    `module` picks the program: the bare base emulator, or `sim_stub.sim_server` (the whole
    simulated robot, whose depth socket is `emu.depth_socket`). Both speak the same JSON lines.
    """

    def __init__(
        self,
        args: list[str] | None = None,
        startup_timeout_s: float = 30.0,  # a loaded machine may take this long to import and bind
        module: str = "sim_stub.base_emulator",
    ) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="safemove-emu-")
        self.dir = Path(self._tmp.name)
        self.link = str(self.dir / "sparkBase")
        self.depth_socket = str(self.dir / "depth.sock")
        self._proc = subprocess.Popen(
            [sys.executable, "-m", module, "--link", self.link, *(args or [])],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None,
            text=True,
            bufsize=1,
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.history: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        ready = self.wait_for("ready", startup_timeout_s)
        self.pty: str = ready["pty"]
        self.pid = self._proc.pid

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            try:
                event = json.loads(line)
            except json.JSONDecodeError:
                event = {"event": "unparsed", "line": line.rstrip("\n")}
            self.history.append(event)
            self.events.put(event)

    def send(self, op: str, **kwargs: Any) -> None:
        assert self._proc.stdin is not None
        self._proc.stdin.write(json.dumps({"op": op, **kwargs}) + "\n")
        self._proc.stdin.flush()

    def wait_for(self, name: str, timeout_s: float = 5.0, **match: Any) -> dict[str, Any]:
        """The next event called `name` whose fields equal `match`; RuntimeError on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise RuntimeError(f"emulator: no '{name}' event {match or ''} within {timeout_s} s")
            try:
                event = self.events.get(timeout=remaining)
            except queue.Empty:
                continue
            if event.get("event") == name and all(event.get(k) == v for k, v in match.items()):
                return event
            if self._proc.poll() is not None and self.events.empty():
                raise RuntimeError(f"emulator exited with {self._proc.returncode}")

    def request(self, op: str, reply: str, timeout_s: float = 5.0, **kwargs: Any) -> dict[str, Any]:
        self.send(op, **kwargs)
        return self.wait_for(reply, timeout_s)

    def truth(self) -> dict[str, Any]:
        return self.request("truth", "truth")

    def close(self) -> int:
        if self._proc.poll() is None:
            try:
                self.send("quit")
                self._proc.wait(timeout=3)
            except (OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        self._tmp.cleanup()
        return self._proc.returncode

    def __enter__(self) -> EmulatorProcess:  # noqa: PYI034 - Python 3.10 has no typing.Self
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

