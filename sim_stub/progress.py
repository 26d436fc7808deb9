"""Progress of long work (evaluation episodes, training steps) on stderr: a tqdm bar with its
ETA when stderr is a terminal, someone watching it; plain lines otherwise (a log file, a pipe,
CI), where a redrawn bar would be a mess of carriage returns. Stdout is left alone: the
commands' last stdout line is their JSON result."""

from __future__ import annotations

import sys
import time
from types import TracebackType
from typing import Any

from tqdm import tqdm


class _Bar(tqdm):
    """tqdm without its monitor thread: eval forks its workers while the bar is up, and a fork
    of a multi-threaded process may inherit a held lock. (miniters=1 instead keeps the bar
    fresh when updates slow down, which the monitor is there for.)"""

    monitor_interval = 0


class Progress:
    """`total` units of work. With a terminal: a bar; without: a status line each time another
    `line_every` units are done (none when it is None: the caller writes its own lines)."""

    def __init__(self, total: int, desc: str, unit: str, line_every: int | None = None) -> None:
        self.total, self.desc, self.unit, self.line_every = total, desc, unit, line_every
        self.done = 0
        self._t0 = time.monotonic()
        self._bar = (_Bar(total=total, desc=desc, unit=unit, file=sys.stderr, miniters=1,
                          dynamic_ncols=True) if sys.stderr.isatty() else None)

    @property
    def plain(self) -> bool:
        """Whether progress goes out as plain lines (no terminal)."""
        return self._bar is None

    def advance(self, n: int = 1, **postfix: Any) -> None:
        """`n` more units done; `postfix` (counts so far) shows after the bar."""
        before, self.done = self.done, self.done + n
        if self._bar is not None:
            if postfix:
                self._bar.set_postfix(postfix, refresh=False)
            self._bar.update(n)
        elif self.line_every is not None:
            crossed = self.done // self.line_every > before // self.line_every
            if crossed or before < self.total <= self.done:
                self.line(self.status())

    def line(self, text: str) -> None:
        """A line on stderr (above the bar when there is one)."""
        if self._bar is not None:
            self._bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    def status(self) -> str:
        """Done of total, rate and ETA, in one line."""
        elapsed = time.monotonic() - self._t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        eta = f"{max(self.total - self.done, 0) / rate:.0f} s" if rate > 0 else "-"
        return (f"{self.desc}: {self.done}/{self.total} {self.unit}s"
                f" ({100 * self.done / max(self.total, 1):.0f} %), {rate:.1f} {self.unit}s/s,"
                f" ETA {eta}")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Progress:  # noqa: PYI034 - Python 3.10 has no typing.Self
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
