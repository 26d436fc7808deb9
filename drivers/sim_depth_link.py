"""Depth frames from the simulator over a Unix stream socket: the wire format and the client.

Wire format (little-endian), one message per frame, no pickles:
    header  "<4sIQdHH6dII": magic b"SMD1", header size, frame_number, t (host monotonic s),
            width, height, fx, fy, cx, cy, depth_unit_m, reserved (0.0), payload bytes, crc32
    payload width·height uint16 Z16 pixels, row-major

A reader thread assembles frames as they arrive (a 848×480 frame is 814 KB, more than a Unix
socket buffers), so the control loop's `poll()` never blocks and no frame is lost while the
loop is busy. Malformed bytes drop the connection (counted) and the client reconnects.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import zlib
from collections import Counter, deque

import numpy as np

from drivers.depth_source import DepthFrame, DepthIntrinsics
from runtime.errors import DeviceError

log = logging.getLogger("safemove.depth.sim")

MAGIC = b"SMD1"
HEADER = struct.Struct("<4sIQdHH6dII")
MAX_PIXELS = 4096 * 4096
QUEUE_LEN = 64  # ~4 s at 15 fps: only reached if the loop stops polling


class LinkFormatError(ValueError):
    """Bytes on the depth link that are not a frame."""


def encode_frame(frame: DepthFrame) -> tuple[bytes, int]:
    """Header + payload for one frame, and the payload's crc32 (for the sender's digest)."""
    k = frame.intrinsics
    depth = np.ascontiguousarray(frame.depth, dtype="<u2")
    if depth.shape != (k.height, k.width):
        raise ValueError(f"depth shape {depth.shape} does not match intrinsics {k.width}x{k.height}")
    payload = depth.tobytes()
    crc = zlib.crc32(payload)
    header = HEADER.pack(
        MAGIC, HEADER.size, frame.frame_number, frame.t, k.width, k.height,
        k.fx, k.fy, k.cx, k.cy, k.depth_unit_m, 0.0, len(payload), crc,
    )
    return header + payload, crc


def decode_header(raw: bytes | bytearray) -> tuple[int, float, DepthIntrinsics, int, int]:
    """(frame_number, t, intrinsics, payload_len, crc32) from a header; LinkFormatError if bad."""
    (magic, size, number, t, width, height, fx, fy, cx, cy, unit, _reserved, payload_len,
     crc) = HEADER.unpack(raw)
    if magic != MAGIC or size != HEADER.size:
        raise LinkFormatError(f"bad header (magic {magic!r}, size {size})")
    if not (0 < width * height <= MAX_PIXELS) or payload_len != 2 * width * height:
        raise LinkFormatError(f"bad frame size {width}x{height} with {payload_len} payload bytes")
    return number, t, DepthIntrinsics(width, height, fx, fy, cx, cy, unit), payload_len, crc


def frame_digest(digest: int, frame_number: int, crc: int) -> int:
    """Running digest over (frame_number, crc32) pairs: sender and receiver compare it."""
    return zlib.crc32(struct.pack("<QI", frame_number, crc), digest)


class SimDepthSource:
    """DepthSource for `safemove sim`: connects to its depth socket and queues every frame."""

    def __init__(self, socket_path: str, reconnect_s: float = 0.5) -> None:
        self._path = socket_path
        self._reconnect_s = reconnect_s
        self._queue: deque[DepthFrame] = deque()
        self._sock: socket.socket | None = None
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.counts: Counter[str] = Counter()
        self.digest = 0

    @property
    def at_end(self) -> bool:
        return False  # a live link never ends; a silent one goes stale

    def start(self) -> None:
        """Connect (a missing socket is a DeviceError) and start the reader thread."""
        try:
            self._sock = self._connect()
        except OSError as exc:
            raise DeviceError(
                f"sim depth link {self._path}: cannot connect ({exc.strerror or exc}); "
                "is `safemove sim` running?"
            ) from None
        self._thread = threading.Thread(target=self._run, name="sim-depth-reader", daemon=True)
        self._thread.start()

    def poll(self) -> DepthFrame | None:
        return self._queue.popleft() if self._queue else None

    def stop(self) -> None:
        self._closing.set()
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass  # already disconnected: nothing to shut down
            sock.close()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _connect(self) -> socket.socket:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
            sock.connect(self._path)
        except OSError:
            sock.close()
            raise
        self.counts["connects"] += 1
        return sock

    def _run(self) -> None:
        while not self._closing.is_set():
            sock = self._sock
            if sock is None:
                if self._closing.wait(self._reconnect_s):
                    return
                try:
                    self._sock = self._connect()
                    log.info("sim depth link %s reconnected", self._path)
                except OSError:
                    continue
                continue
            try:
                self._read_frames(sock)
            except (OSError, LinkFormatError, EOFError) as exc:
                if self._closing.is_set():
                    return
                self.counts["disconnects"] += 1
                if isinstance(exc, LinkFormatError):
                    self.counts["format_errors"] += 1
                log.warning("sim depth link %s lost: %s", self._path, exc or type(exc).__name__)
                self._sock = None
                sock.close()

    def _read_frames(self, sock: socket.socket) -> None:
        while not self._closing.is_set():
            number, t, intrinsics, payload_len, crc = decode_header(recv_exact(sock, HEADER.size))
            payload = recv_exact(sock, payload_len)
            if zlib.crc32(payload) != crc:
                raise LinkFormatError(f"frame {number}: payload checksum mismatch")
            depth = np.frombuffer(payload, dtype="<u2").reshape(intrinsics.height, intrinsics.width)
            if len(self._queue) >= QUEUE_LEN:
                self._queue.popleft()
                self.counts["queue_overflows"] += 1
            self._queue.append(DepthFrame(depth, t, number, intrinsics))
            self.counts["frames"] += 1
            self.digest = frame_digest(self.digest, number, crc)


def recv_exact(sock: socket.socket, n: int) -> bytearray:
    """Exactly n bytes from a stream socket; EOFError when the peer closes first."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = sock.recv_into(view[got:], n - got)
        if k == 0:
            raise EOFError("the simulator closed the depth link")
        got += k
    return buf

