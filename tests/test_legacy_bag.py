"""A legacy ROS 1 RealSense `.bag` (what realsense-viewer used to write) plays back bit-exact.

pyrealsense2 can no longer write one, so tests/legacy_bag.py builds it in librealsense's ROS 1
layout; the file is played through the real SDK reader by PlaybackDepthSource.
"""

from __future__ import annotations

import time

import numpy as np
import pyrealsense2 as rs
import pytest

# pytest's default import mode puts tests/ (no __init__.py) on sys.path
from legacy_bag import write_legacy_depth_bag

from drivers.realsense.playback import PlaybackDepthSource
from runtime.config.settings import CameraMount, LimitsConfig
from runtime.types import Twist
from sim_stub.recording import simulated_frames
from sim_stub.scenario import load_scenario

FPS = 30
FIRST_FRAME_NUMBER = 100  # not 0: shows the frame number comes from the file, not a counter


@pytest.fixture(scope="module")
def expected():
    frames = list(simulated_frames(load_scenario("paper_b"), 10, float(FPS), Twist(0.2, 0.1),
                                   CameraMount(), LimitsConfig()))
    # the scene moves: equality below is not about one still image
    assert not np.array_equal(frames[0].depth, frames[-1].depth)
    return frames


@pytest.fixture
def legacy_bag(tmp_path, expected):
    path = tmp_path / "paper_b.bag"
    write_legacy_depth_bag(
        path,
        [(f.depth, f.t * 1000.0, FIRST_FRAME_NUMBER + f.frame_number) for f in expected],
        expected[0].intrinsics,
        FPS,
    )
    assert path.read_bytes()[:13] == b"#ROSBAG V2.0\n"  # a ROS 1 bag, not rosbag2
    return path


def play_all(path, timeout_s: float = 10.0) -> tuple[PlaybackDepthSource, list]:
    source = PlaybackDepthSource(path)
    source.start()
    frames = []
    deadline = time.monotonic() + timeout_s
    try:
        while not source.at_end:
            assert time.monotonic() < deadline, f"playback of {path} never reached its end"
            frame = source.poll()
            if frame is not None:
                frames.append(frame)
    finally:
        source.stop()
    return source, frames


def assert_plays_back(path, expected) -> None:
    source, played = play_all(path)
    assert source.at_end
    assert len(played) == len(expected) == 10
    want_k = expected[0].intrinsics
    got_k = source.intrinsics
    assert (got_k.width, got_k.height) == (want_k.width, want_k.height)
    for name in ("fx", "fy", "cx", "cy", "depth_unit_m"):  # the SDK keeps these as float32
        assert getattr(got_k, name) == pytest.approx(getattr(want_k, name), rel=1e-6), name
    for want, got in zip(expected, played):
        assert got.frame_number == FIRST_FRAME_NUMBER + want.frame_number
        assert got.t == pytest.approx(want.t, abs=1e-9)  # header.stamp, to the nanosecond
        assert got.depth.dtype == np.uint16
        assert np.array_equal(got.depth, want.depth)


def test_legacy_ros1_bag_plays_back_bit_exact(legacy_bag, expected):
    assert_plays_back(legacy_bag, expected)


@pytest.mark.skipif(not hasattr(rs.context, "convert_bag_to_db3"),
                    reason="this pyrealsense2 has no context.convert_bag_to_db3")
def test_legacy_bag_converted_to_db3_plays_back_bit_exact(legacy_bag, expected, tmp_path):
    db3 = tmp_path / "converted.db3"
    rs.context().convert_bag_to_db3(str(legacy_bag), str(db3))
    assert db3.is_file()
    assert_plays_back(db3, expected)
