"""A fault injector on the sim depth link: frames from `safemove sim` pass through, and on
request the next frames are altered the way a failing or lying camera would alter them.

Altered frames keep valid framing and a correct payload checksum, so they reach the runtime's
frame handling rather than being dropped as link noise. Used by the depth fault HIL tests and
the fault-injection suite; a real Unix socket on both sides.
"""

from __future__ import annotations

import contextlib
import dataclasses
import select
import socket
import threading
import time
from pathlib import Path

import numpy as np

from drivers.sim_depth_link import HEADER, decode_header, encode_frame, recv_exact
from runtime.types import DepthFrame

FAULTS = ("nan_stamp", "stamp_offset", "saturate", "zero", "stall")


def alter(frame: DepthFrame, kind: str, offset_s: float = 0.0) -> DepthFrame | None:
    """The frame as the fault `kind` delivers it (None: not delivered at all)."""
    if kind == "stall":
        return None
    if kind == "nan_stamp":
        return dataclasses.replace(frame, t=float("nan"))
    if kind == "stamp_offset":
        return dataclasses.replace(frame, t=frame.t + offset_s)
    if kind == "saturate":
        return dataclasses.replace(frame, depth=np.full_like(frame.depth, 0xFFFF))
    if kind == "zero":
        return dataclasses.replace(frame, depth=np.zeros_like(frame.depth))
    raise ValueError(f"unknown depth fault {kind!r}; one of {', '.join(FAULTS)}")


class DepthFaultProxy:
    """Listens on `path` for the runtime, forwards `upstream`'s frames. `inject(kind, frames)`
    alters the next `frames` frames; `injected_at` is the host monotonic time the first altered
    frame was due (sent, or withheld for a stall)."""

    def __init__(self, upstream: str, path: str) -> None:
        self.upstream = upstream
        self.path = path
        self._lock = threading.Lock()
        self._plan: list[tuple[str, int, float]] = []
        self.injected_at: float | None = None
        self.forwarded = 0
        self.altered = 0
        self._closing = threading.Event()
        with contextlib.suppress(FileNotFoundError):
            Path(path).unlink()
        self._listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._listener.bind(path)
        self._listener.listen(1)
        self._thread = threading.Thread(target=self._run, name="depth-fault-proxy", daemon=True)
        self._thread.start()

    def inject(self, kind: str, frames: int = 1, offset_s: float = 0.0) -> None:
        if kind not in FAULTS:
            raise ValueError(f"unknown depth fault {kind!r}; one of {', '.join(FAULTS)}")
        with self._lock:
            self._plan.append((kind, frames, offset_s))

    @property
    def pending(self) -> bool:
        with self._lock:
            return bool(self._plan)

    def close(self) -> None:
        self._closing.set()
        self._listener.close()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(FileNotFoundError):
            Path(self.path).unlink()

    def __enter__(self) -> DepthFaultProxy:  # noqa: PYI034 - Python 3.10 has no typing.Self
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        try:
            client, _ = self._listener.accept()
        except OSError:
            return  # closed before the runtime connected
        up = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        with client, up:
            up.connect(self.upstream)
            while not self._closing.is_set():
                if not select.select([up], [], [], 0.2)[0]:
                    continue
                try:
                    frame = self._read(up)
                except (OSError, EOFError):
                    return
                out = self._apply(frame)
                if out is not None:
                    try:
                        client.sendall(encode_frame(out)[0])
                    except OSError:
                        return
                    self.forwarded += 1

    def _read(self, sock: socket.socket) -> DepthFrame:
        number, t, intrinsics, payload_len, _crc = decode_header(recv_exact(sock, HEADER.size))
        payload = recv_exact(sock, payload_len)
        depth = np.frombuffer(payload, dtype="<u2").reshape(intrinsics.height, intrinsics.width)
        return DepthFrame(depth, t, number, intrinsics)

    def _apply(self, frame: DepthFrame) -> DepthFrame | None:
        with self._lock:
            if not self._plan:
                return frame
            kind, left, offset_s = self._plan[0]
            if left <= 1:
                self._plan.pop(0)
            else:
                self._plan[0] = (kind, left - 1, offset_s)
        if self.injected_at is None:
            self.injected_at = time.monotonic()
        self.altered += 1
        return alter(frame, kind, offset_s)
