"""Frames for the camera calibration: depth from any DepthSource, infrared for the board.

Depth comes through the runtime's one interface (live D435, the simulator's depth link, or a
recording via PlaybackDepthSource). The ChArUco board is detected in the left infrared image,
which the depth sources do not carry, so infrared is read here: from a recording's infrared
stream, or from the live D435 with its dot projector off (the dots break the marker borders).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
import pyrealsense2 as rs

from drivers.depth_source import DepthSource
from runtime.config.settings import DepthConfig
from runtime.errors import DeviceError, UserError
from runtime.types import DepthIntrinsics

POLL_S = 0.005


@dataclass
class Frames:
    """Images of one still scene and the intrinsics they share."""

    images: list[np.ndarray]
    intrinsics: DepthIntrinsics | None
    ended: bool  # the source ran out (end of a recording) before `count`


def collect_depth(source: DepthSource, count: int, timeout_s: float, skip: int = 0,
                  drain: bool = False) -> Frames:
    """Up to `count` depth frames (after dropping `skip`: a live camera's first frames come
    before its exposure settles); stops at the end of a recording or after `timeout_s`.
    `drain` reads a recording to its end before stopping it: stopping a non-real-time playback
    mid-file has crashed librealsense 2.59 here (segfault in pipeline.stop)."""
    frames: list[np.ndarray] = []
    intrinsics = None
    seen = 0
    source.start()
    try:
        deadline = time.monotonic() + timeout_s
        while ((len(frames) < count or drain) and not source.at_end
               and time.monotonic() < deadline):
            frame = source.poll()
            if frame is None:
                time.sleep(POLL_S)
                continue
            seen += 1
            if skip < seen and len(frames) < count:
                frames.append(frame.depth)
                intrinsics = frame.intrinsics
    finally:
        source.stop()
    return Frames(frames, intrinsics, source.at_end)


def _intrinsics(profile: rs.video_stream_profile, unit: float = 0.001) -> DepthIntrinsics:
    i = profile.get_intrinsics()
    return DepthIntrinsics(i.width, i.height, i.fx, i.fy, i.ppx, i.ppy, unit)


def _read_infrared(pipe: rs.pipeline, count: int, timeout_s: float) -> list[np.ndarray]:
    images: list[np.ndarray] = []
    deadline = time.monotonic() + timeout_s
    while len(images) < count and time.monotonic() < deadline:
        ok, frames = pipe.try_wait_for_frames(200)
        if not ok:
            continue
        ir = frames.first_or_default(rs.stream.infrared)
        if ir:
            images.append(np.asanyarray(ir.get_data()).copy())
        del ir, frames
    return images


def recording_with_infrared(path: str | os.PathLike, count: int, timeout_s: float = 30.0
                            ) -> tuple[Frames, Frames]:
    """Up to `count` depth and infrared images of a .db3 recording, read in one playback to
    its end (see `collect_depth`); UserError if it has no infrared stream."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise UserError(f"{path}: recording not found")
    pipe = rs.pipeline()
    cfg = rs.config()
    try:
        cfg.enable_device_from_file(path, repeat_playback=False)
        cfg.enable_stream(rs.stream.depth)
        cfg.enable_stream(rs.stream.infrared)
        cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(False)
        profile = pipe.start(cfg)
    except RuntimeError:
        raise UserError(
            f"{path}: the recording has no infrared stream, which --board needs (record the"
            " left infrared stream with the depth, or calibrate without --board)") from None
    depths: list[np.ndarray] = []
    irs: list[np.ndarray] = []
    try:
        playback = profile.get_device().as_playback()
        playback.set_real_time(False)
        unit = profile.get_device().first_depth_sensor().get_depth_scale()
        depth_k = _intrinsics(profile.get_stream(rs.stream.depth).as_video_stream_profile(),
                              unit)
        ir_k = _intrinsics(profile.get_stream(rs.stream.infrared).as_video_stream_profile())
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:  # to the end: see collect_depth's `drain`
            ok, frames = pipe.try_wait_for_frames(200)
            if not ok:
                if playback.current_status() == rs.playback_status.stopped:
                    break
                continue
            depth = frames.first_or_default(rs.stream.depth)
            ir = frames.first_or_default(rs.stream.infrared)
            if depth and len(depths) < count:
                depths.append(np.asanyarray(depth.get_data()).copy())
            if ir and len(irs) < count:
                irs.append(np.asanyarray(ir.get_data()).copy())
            del depth, ir, frames
    finally:
        pipe.stop()
    return (Frames(depths, depth_k, len(depths) < count),
            Frames(irs, ir_k, len(irs) < count))


def infrared_from_d435(cfg: DepthConfig, count: int, timeout_s: float = 10.0) -> Frames:
    """Up to `count` left infrared images from the live D435, projector off while reading."""
    try:
        devices = list(rs.context().query_devices())
    except RuntimeError as exc:
        raise DeviceError(f"D435: the RealSense SDK cannot list devices: {exc}") from None
    if not devices:
        raise DeviceError("D435: no RealSense device found for the infrared image (check the"
                          " USB 3 cable and the udev rule)")
    pipe = rs.pipeline()
    config = rs.config()
    if cfg.serial:
        config.enable_device(cfg.serial)
    config.enable_stream(rs.stream.infrared, 1, cfg.width, cfg.height, rs.format.y8, cfg.fps)
    try:
        profile = pipe.start(config)
    except RuntimeError as exc:
        raise DeviceError(f"D435: cannot stream infrared {cfg.width}x{cfg.height} @ {cfg.fps}"
                          f" Hz: {exc}") from None
    sensor = profile.get_device().first_depth_sensor()
    emitter = None
    try:
        if sensor.supports(rs.option.emitter_enabled):
            emitter = sensor.get_option(rs.option.emitter_enabled)
            sensor.set_option(rs.option.emitter_enabled, 0)
        stream = profile.get_stream(rs.stream.infrared, 1).as_video_stream_profile()
        intrinsics = _intrinsics(stream)
        _read_infrared(pipe, 5, timeout_s)  # the projector needs a few frames to go dark
        images = _read_infrared(pipe, count, timeout_s)
    finally:
        if emitter is not None:
            sensor.set_option(rs.option.emitter_enabled, emitter)
        pipe.stop()
    return Frames(images, intrinsics, False)
