"""A pty proxy that corrupts serial bytes in flight: fault injection for the Spark base link.

    python -m sim_stub.serial_proxy --upstream /tmp/sm/sparkBase --link /tmp/sm/proxied --rate 0.03

The host opens `--link` as if it were /dev/sparkBase; the proxy opens `--upstream` (the base
emulator's pty) and copies bytes both ways. A chosen fraction of them is changed on the way:
flipped in one bit (line noise on a UART) or replaced by another value. No byte is inserted
or deleted (while the host reads), so frame boundaries stay where the sender put them and what
gets past the parser is exactly what an 8-bit checksum fails to catch. Corruption is seeded and depends only
on a byte's position in its direction's stream, never on how reads happen to be chunked, so a
run is reproducible byte for byte as far as the stream itself is.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import selectors
import signal
import sys
import threading
import tty
from pathlib import Path
from typing import Literal

MODES = ("flip", "replace")
DIRECTIONS = ("both", "feedback")
READ_CHUNK = 4096
MAX_PENDING = 4096  # bytes held for a reader that is not reading, like a serial driver's buffer

Mode = Literal["flip", "replace"]
Direction = Literal["both", "feedback"]


class ByteCorrupter:
    """Corrupts each byte of one direction's stream with probability `rate`, seeded.

    The gap to the next corrupted byte is drawn from the geometric distribution, so the cost is
    per corrupted byte, not per byte, and the draws happen in stream order whatever the chunks.
    """

    def __init__(self, rate: float, seed: int, mode: Mode = "flip") -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        self.mode = mode
        self._rng = random.Random(seed)
        self._pos = 0  # stream position of the next byte to arrive
        self.rate = rate
        self.bytes = 0
        self.corrupted = 0

    @property
    def rate(self) -> float:
        return self._rate

    @rate.setter
    def rate(self, rate: float) -> None:
        """Change the rate from the next byte on (a burst of noise starts or ends)."""
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"rate must be within [0, 1], got {rate}")
        self._rate = rate
        self._next = self._pos + self._gap()  # stream position of the next byte to corrupt

    def _gap(self) -> float:
        if self._rate == 0.0:
            return math.inf
        if self._rate == 1.0:
            return 0
        return int(math.log(1.0 - self._rng.random()) / math.log(1.0 - self._rate))

    def __call__(self, data: bytes) -> bytes:
        """The same bytes with this stretch's share corrupted (always to a different value)."""
        out = bytearray(data)
        end = self._pos + len(out)
        while self._next < end:
            i = int(self._next) - self._pos
            if self.mode == "flip":
                out[i] ^= 1 << self._rng.randrange(8)
            else:
                out[i] ^= self._rng.randrange(1, 256)
            self.corrupted += 1
            self._next += 1 + self._gap()
        self._pos = end
        self.bytes += len(out)
        return bytes(out)


class CorruptingProxy:
    """Copies bytes between the base's pty (`upstream`) and a new pty at `link`, corrupting them.

    Feedback (base → host) is always corrupted at `rate`; commands (host → base) too when
    `direction` is "both". Each direction has its own seeded generator, so how the host's writes
    interleave with the base's frames does not move the corruption. Runs on its own thread:
    `with CorruptingProxy(...) as proxy: ...`. It does not follow the upstream pty across a
    reopen (an unplug ends the proxy, as it would end a real cable).
    """

    def __init__(
        self,
        upstream: str | Path,
        link: str | Path,
        rate: float,
        seed: int = 0,
        mode: Mode = "flip",
        direction: Direction = "both",
    ) -> None:
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
        self.link = Path(link)
        self.direction = direction
        self.feedback = ByteCorrupter(rate, 2 * seed, mode)
        self.commands = ByteCorrupter(rate if direction == "both" else 0.0, 2 * seed + 1, mode)
        self._upstream = os.open(upstream, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self._upstream)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # raw at once: echo or CR/LF translation would alter frames
        os.set_blocking(self._master, False)
        self.pty = os.ttyname(self._slave)
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(self.pty, tmp)
        os.replace(tmp, self.link)
        self.overflow = 0  # bytes lost because nobody read them (see `_run`)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="serial-proxy", daemon=True)
        self._thread.start()

    def set_rate(self, rate: float) -> None:
        """Change the corruption rate from the next byte on (a burst of noise begins or ends)."""
        self.feedback.rate = rate
        if self.direction == "both":
            self.commands.rate = rate

    @property
    def running(self) -> bool:
        """False once the upstream pty has gone (or after close)."""
        return self._thread.is_alive()

    def stats(self) -> dict[str, int]:
        """Bytes seen and corrupted per direction, and bytes lost to a reader that did not read."""
        return {
            "feedback_bytes": self.feedback.bytes,
            "feedback_corrupted": self.feedback.corrupted,
            "command_bytes": self.commands.bytes,
            "command_corrupted": self.commands.corrupted,
            "overflow": self.overflow,
        }

    def close(self) -> None:
        """Stop copying, remove the link and close both ptys."""
        if self._thread.is_alive():
            os.write(self._wake_w, b"x")
            self._thread.join(timeout=2.0)
        if self.link.is_symlink() and os.readlink(self.link) == self.pty:
            self.link.unlink()
        for fd in (self._upstream, self._master, self._slave, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> CorruptingProxy:  # noqa: PYI034 - Python 3.10 has no typing.Self
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        """Forward whatever is readable; a write that would block keeps its tail for later, so a
        slow reader delays bytes but never loses or reorders them. Only a reader that stops
        reading altogether (the host not attached yet) loses the oldest bytes beyond
        `MAX_PENDING`, as a serial driver's buffer would, rather than get seconds-old frames."""
        routes = {self._upstream: (self._master, self.feedback),
                  self._master: (self._upstream, self.commands)}
        pending = {self._upstream: b"", self._master: b""}  # keyed by destination fd
        with selectors.DefaultSelector() as sel:
            sel.register(self._wake_r, selectors.EVENT_READ)
            for fd in routes:
                sel.register(fd, selectors.EVENT_READ)
            while True:
                for key, events in sel.select():
                    if key.fd == self._wake_r:
                        return
                    if events & selectors.EVENT_READ:
                        dest, corrupt = routes[key.fd]
                        try:
                            data = os.read(key.fd, READ_CHUNK)
                        except BlockingIOError:
                            data = b""
                        except OSError:  # the upstream pty closed (unplug): stop like a cable
                            return
                        waiting = pending[dest] + corrupt(data)
                        self.overflow += max(0, len(waiting) - MAX_PENDING)
                        pending[dest] = waiting[-MAX_PENDING:]
                    for dest, waiting in list(pending.items()):
                        if waiting:
                            with contextlib.suppress(BlockingIOError):
                                pending[dest] = waiting[os.write(dest, waiting):]
                        sel.modify(dest, selectors.EVENT_READ
                                   | (selectors.EVENT_WRITE if pending[dest] else 0))


def main(argv: list[str] | None = None) -> int:
    """CLI: run a proxy until SIGTERM/SIGINT; one JSON line when ready, one with stats at exit."""
    p = argparse.ArgumentParser(prog="python -m sim_stub.serial_proxy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--upstream", required=True, help="the base's serial device (emulator link)")
    p.add_argument("--link", required=True, type=Path, help="symlink the host opens instead")
    p.add_argument("--rate", type=float, required=True, help="fraction of bytes corrupted, 0..1")
    p.add_argument("--seed", type=int, default=0, help="seed of the corruption")
    p.add_argument("--mode", choices=MODES, default="flip",
                   help="flip one bit (line noise) or replace the byte with another value")
    p.add_argument("--direction", choices=DIRECTIONS, default="both",
                   help="corrupt both directions or only the base's feedback")
    args = p.parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        proxy = CorruptingProxy(args.upstream, args.link, args.rate, args.seed, args.mode,
                                args.direction)
    except (OSError, ValueError) as exc:
        print(f"serial proxy: cannot start: {exc}", file=sys.stderr)
        return 2
    with proxy:
        print(json.dumps({"event": "ready", "pty": proxy.pty, "link": str(proxy.link)}), flush=True)
        while proxy.running and not stop.wait(0.5):
            pass
        print(json.dumps({"event": "stats", **proxy.stats()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
