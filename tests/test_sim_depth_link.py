"""The sim depth link: frames round-trip; malformed bytes drop the connection and it reconnects."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from drivers.sim_depth_link import (
    HEADER,
    LinkFormatError,
    SimDepthSource,
    decode_header,
    encode_frame,
)
from runtime.errors import DeviceError
from runtime.types import DepthFrame, DepthIntrinsics

K = DepthIntrinsics(8, 6, 5.0, 5.0, 4.0, 3.0, 0.001)


def frame(n: int) -> DepthFrame:
    rng = np.random.default_rng(n)
    return DepthFrame(rng.integers(0, 65535, (6, 8), dtype=np.uint16), 100.0 + n, n, K)


def wait_frames(source: SimDepthSource, count: int, timeout: float = 5.0) -> list[DepthFrame]:
    got: list[DepthFrame] = []
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        f = source.poll()
        if f is None:
            time.sleep(0.01)
        else:
            got.append(f)
    return got


def test_header_rejects_garbage():
    with pytest.raises(LinkFormatError):
        decode_header(b"NOPE" + bytes(HEADER.size - 4))


def test_frames_round_trip_and_garbage_forces_a_reconnect(tmp_path):
    path = str(tmp_path / "depth.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(2)
    source = SimDepthSource(path, reconnect_s=0.05)
    source.start()
    try:
        conn, _ = server.accept()
        conn.sendall(encode_frame(frame(1))[0] + encode_frame(frame(2))[0])
        first = wait_frames(source, 2)
        assert [f.frame_number for f in first] == [1, 2]
        assert np.array_equal(first[1].depth, frame(2).depth) and first[1].t == 102.0
        assert first[1].intrinsics == K
        conn.sendall(b"\x00garbage that is not a header" + bytes(HEADER.size))
        conn2, _ = server.accept()  # the client dropped the bad stream and came back
        conn2.sendall(encode_frame(frame(3))[0])
        assert [f.frame_number for f in wait_frames(source, 1)] == [3]
        assert source.counts["format_errors"] == 1 and source.counts["connects"] == 2
        conn.close()
        conn2.close()
    finally:
        source.stop()
        server.close()


def test_missing_socket_is_a_device_error(tmp_path):
    with pytest.raises(DeviceError, match="safemove sim"):
        SimDepthSource(str(tmp_path / "absent.sock")).start()
