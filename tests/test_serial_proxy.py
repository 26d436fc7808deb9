"""The corrupting serial proxy: the byte corrupter's statistics and determinism, and the pty
proxy between a stand-in base (a pty the test writes) and a host (the test reading the link)."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import termios
import time
import tty
from pathlib import Path

import pytest

from sim_stub.serial_proxy import ByteCorrupter, CorruptingProxy

DATA = random.Random(0).randbytes(200_000)


@pytest.mark.parametrize("mode", ["flip", "replace"])
@pytest.mark.parametrize("rate", [0.01, 0.1])
def test_corrupts_the_given_share_of_bytes_in_place(rate: float, mode: str) -> None:
    out = ByteCorrupter(rate, seed=1, mode=mode)(DATA)
    assert len(out) == len(DATA)  # nothing inserted or deleted
    changed = [(a, b) for a, b in zip(DATA, out) if a != b]
    assert len(changed) == pytest.approx(rate * len(DATA), rel=0.1)
    if mode == "flip":
        assert all((a ^ b).bit_count() == 1 for a, b in changed)
    else:
        assert any((a ^ b).bit_count() > 1 for a, b in changed)


def test_the_corruption_depends_on_the_seed_and_the_byte_position_only() -> None:
    whole = ByteCorrupter(0.03, seed=5)(DATA)
    chunked = ByteCorrupter(0.03, seed=5)
    cuts = sorted(random.Random(1).sample(range(1, len(DATA)), 500))
    pieces = [DATA[a:b] for a, b in zip([0, *cuts], [*cuts, len(DATA)])]
    assert b"".join(chunked(p) for p in pieces) == whole
    assert ByteCorrupter(0.03, seed=6)(DATA) != whole


def test_a_rate_change_applies_from_the_next_byte() -> None:
    c = ByteCorrupter(0.0, seed=2)
    assert c(DATA[:1000]) == DATA[:1000]
    c.rate = 1.0
    assert all(a != b for a, b in zip(c(DATA[1000:1100]), DATA[1000:1100]))
    c.rate = 0.0
    assert c(DATA[1100:2000]) == DATA[1100:2000]
    assert c.corrupted == 100 and c.bytes == 2000
    with pytest.raises(ValueError, match="rate"):
        c.rate = 1.5


def read_exactly(fd: int, n: int, timeout: float = 5.0) -> bytes:
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        try:
            out += os.read(fd, n - len(out))
        except BlockingIOError:
            time.sleep(0.005)
    return out


def write_all(fd: int, data: bytes, timeout: float = 5.0) -> None:
    """Write to a non-blocking pty, waiting while its buffer is full (a busy proxy thread)."""
    deadline = time.monotonic() + timeout
    while data and time.monotonic() < deadline:
        try:
            data = data[os.write(fd, data):]
        except BlockingIOError:
            time.sleep(0.005)
    assert not data, "the pty did not drain"


def open_host(link: Path) -> int:
    fd = os.open(link, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    return fd


@pytest.mark.parametrize(("direction", "commands_changed"), [("both", True), ("feedback", False)])
def test_the_proxy_copies_both_ways_and_corrupts_as_told(
        pty_pair, tmp_path: Path, direction: str, commands_changed: bool) -> None:
    base, upstream = pty_pair
    data = DATA[:20_000]
    with CorruptingProxy(upstream, tmp_path / "link", rate=0.05, seed=3,
                         direction=direction) as proxy:  # type: ignore[arg-type]
        assert os.readlink(proxy.link) == proxy.pty
        host = open_host(proxy.link)
        try:
            feedback = b""
            for i in range(0, len(data), 1000):  # in pieces, as a base writes frames
                write_all(base, data[i:i + 1000])
                feedback += read_exactly(host, 1000)
            write_all(host, data[:5000])
            commands = read_exactly(base, 5000)
        finally:
            os.close(host)
        stats = proxy.stats()
    assert not (tmp_path / "link").exists()
    assert len(feedback) == len(data)
    assert feedback == ByteCorrupter(0.05, seed=2 * 3)(data)  # the feedback direction's stream
    assert len(commands) == 5000 and (commands != data[:5000]) == commands_changed
    assert stats["feedback_bytes"] == len(data) and stats["command_bytes"] == 5000
    assert stats["feedback_corrupted"] == sum(a != b for a, b in zip(feedback, data))


def test_a_host_that_does_not_read_gets_recent_bytes_not_a_backlog(pty_pair, tmp_path: Path):
    base, upstream = pty_pair
    with CorruptingProxy(upstream, tmp_path / "link", rate=0.0) as proxy:
        for i in range(0, len(DATA), 2000):  # 200 kB while nobody has the link open
            write_all(base, DATA[i:i + 2000])
            time.sleep(0.001)
        deadline = time.monotonic() + 5
        while proxy.stats()["feedback_bytes"] < len(DATA) and time.monotonic() < deadline:
            time.sleep(0.01)
        host = open_host(proxy.link)
        try:
            termios.tcflush(host, termios.TCIFLUSH)  # what the host does on opening the port
            got = read_exactly(host, len(DATA), timeout=0.5)
        finally:
            os.close(host)
        assert proxy.overflow > 0  # beyond what the kernel's pty buffer held
    assert 0 < len(got) <= 4096 and DATA.endswith(got)


def test_the_cli_reports_ready_and_its_counts_on_sigterm(pty_pair, tmp_path: Path) -> None:
    base, upstream = pty_pair
    link = tmp_path / "link"
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim_stub.serial_proxy", "--upstream", upstream, "--link", str(link),
         "--rate", "1", "--direction", "feedback"],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout is not None
        ready = json.loads(proc.stdout.readline())
        assert ready == {"event": "ready", "pty": os.readlink(link), "link": str(link)}
        host = open_host(link)
        try:
            write_all(base, b"\x00" * 100)
            assert all(b != 0 for b in read_exactly(host, 100))  # rate 1: every byte changed
        finally:
            os.close(host)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
        stats = json.loads(proc.stdout.readline())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert stats["feedback_corrupted"] == stats["feedback_bytes"] == 100
    assert not link.exists()


def test_the_cli_refuses_a_missing_upstream_with_exit_2(tmp_path: Path) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "sim_stub.serial_proxy", "--upstream", str(tmp_path / "none"),
         "--link", str(tmp_path / "link"), "--rate", "0.01"],
        check=False, capture_output=True, text=True, timeout=30,
    )
    assert run.returncode == 2 and "cannot start" in run.stderr
