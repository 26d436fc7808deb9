"""The live RealSense D435 as a DepthSource, with post-processing and a stall recovery ladder.

A worker thread owns the pipeline: it waits for frames, runs the configured filters in the
SDK's recommended order, copies the pixels out of the SDK's pool at once, and queues them. The
control loop's `poll()` only pops that queue. Stalls climb a ladder: a few timeouts, then a
pipeline restart, then a hardware reset with a bounded wait for re-enumeration (the SDK's own
wait has no timeout in Python). Every step is logged and counted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from typing import Any

import numpy as np
import pyrealsense2 as rs

from runtime.config.devices import DepthConfig
from runtime.errors import DeviceError
from runtime.types import DepthFrame, DepthIntrinsics

log = logging.getLogger("safemove.depth.d435")

QUEUE_LEN = 8  # the loop keeps only the newest; more than a few queued means it is behind
REENUMERATE_TIMEOUT_S = 15.0
MIN_RANGE_M = 0.17  # D435 at 848x480: closer is unknown, never free


def _find_device(serial: str) -> Any:
    """The device to open; DeviceError naming what is wrong when there is none (or ambiguity)."""
    try:
        devices = list(rs.context().query_devices())
    except RuntimeError as exc:
        raise DeviceError(f"D435: the RealSense SDK cannot list devices: {exc}") from None
    found = {d.get_info(rs.camera_info.serial_number): d for d in devices}
    if not found:
        raise DeviceError(
            "D435: no RealSense device found (check the USB 3 cable, the udev rule for the video"
            " group, and that no other process holds the camera)"
        )
    if serial:
        if serial not in found:
            raise DeviceError(f"D435 serial {serial}: not connected (found: {', '.join(found)})")
        return found[serial]
    if len(found) > 1:
        raise DeviceError(f"D435: several cameras connected ({', '.join(found)}): set depth.serial")
    return next(iter(found.values()))


def build_filters(cfg: DepthConfig) -> list[Any]:
    """SDK post-processing blocks in the recommended order (decimation → threshold → disparity →
    spatial → temporal → depth → hole filling); spatial and temporal run in disparity space."""
    filters: list[Any] = []
    if cfg.decimation > 1:
        decimation = rs.decimation_filter()
        decimation.set_option(rs.option.filter_magnitude, cfg.decimation)
        filters.append(decimation)
    threshold = rs.threshold_filter()
    threshold.set_option(rs.option.min_distance, MIN_RANGE_M)
    threshold.set_option(rs.option.max_distance, 10.0)
    filters.append(threshold)
    if cfg.spatial_filter or cfg.temporal_filter:
        filters.append(rs.disparity_transform(True))
        if cfg.spatial_filter:
            filters.append(rs.spatial_filter())
        if cfg.temporal_filter:
            filters.append(rs.temporal_filter())
        filters.append(rs.disparity_transform(False))
    if cfg.hole_filling:
        filters.append(rs.hole_filling_filter())
    return filters


class LiveD435Source:
    """DepthSource for the live camera."""

    def __init__(self, cfg: DepthConfig) -> None:
        self._cfg = cfg
        self._queue: deque[DepthFrame] = deque()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._pipeline: Any = None
        self._rs_config: Any = None
        self._serial = cfg.serial
        self._filters = build_filters(cfg)
        self._depth_unit = 0.001
        self.counts: Counter[str] = Counter()

    @property
    def at_end(self) -> bool:
        return False  # a camera never ends; a silent one goes stale and is recovered

    def start(self) -> None:
        """Open the camera (DeviceError with the reason if it cannot be) and start the worker."""
        device = _find_device(self._cfg.serial)
        self._serial = device.get_info(rs.camera_info.serial_number)
        self._rs_config = rs.config()
        self._rs_config.enable_device(self._serial)
        self._rs_config.enable_stream(
            rs.stream.depth, self._cfg.width, self._cfg.height, rs.format.z16, self._cfg.fps
        )
        try:
            self._start_pipeline()
        except RuntimeError as exc:
            raise DeviceError(
                f"D435 {self._serial}: cannot stream depth {self._cfg.width}x{self._cfg.height}"
                f" @ {self._cfg.fps} Hz: {exc}"
            ) from None
        self._thread = threading.Thread(target=self._run, name="d435-reader", daemon=True)
        self._thread.start()

    def poll(self) -> DepthFrame | None:
        return self._queue.popleft() if self._queue else None

    def stop(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._stop_pipeline()

    # --- worker --------------------------------------------------------------------------------

    def _start_pipeline(self) -> None:
        self._pipeline = rs.pipeline()
        profile = self._pipeline.start(self._rs_config)
        sensor = profile.get_device().first_depth_sensor()
        self._depth_unit = sensor.get_depth_scale()
        log.info("D435 %s streaming depth at %dx%d @ %d Hz (unit %.4g m)", self._serial,
                 self._cfg.width, self._cfg.height, self._cfg.fps, self._depth_unit)

    def _stop_pipeline(self) -> None:
        pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError as exc:  # stopping a pipeline whose device vanished
                log.debug("D435 pipeline stop: %s", exc)

    def _run(self) -> None:
        stalls = restarts = 0
        timeout_ms = int(self._cfg.frame_timeout_s * 1000)
        while not self._closing.is_set():
            if self._pipeline is None and not self._recover(restarts):
                continue
            ok, frames = self._pipeline.try_wait_for_frames(timeout_ms)
            if not ok:
                stalls += 1
                self.counts["stalls"] += 1
                log.warning("D435 %s: no frame for %.1f s (%d in a row)", self._serial,
                            self._cfg.frame_timeout_s, stalls)
                if stalls >= self._cfg.restart_after_stalls:
                    stalls = 0
                    restarts += 1
                    self._stop_pipeline()
                continue
            stalls = restarts = 0
            self._take(frames)

    def _recover(self, restarts: int) -> bool:
        """Restart the pipeline; after `reset_after_restarts` failed restarts, reset the device."""
        try:
            if restarts > self._cfg.reset_after_restarts:
                self._hardware_reset()
            self.counts["restarts"] += 1
            self._start_pipeline()
            return True
        except (RuntimeError, DeviceError) as exc:
            log.warning("D435 %s: recovery failed: %s", self._serial, exc)
            self._closing.wait(1.0)
            return False

    def _hardware_reset(self) -> None:
        log.warning("D435 %s: hardware reset", self._serial)
        self.counts["hardware_resets"] += 1
        _find_device(self._serial).hardware_reset()
        deadline = time.monotonic() + REENUMERATE_TIMEOUT_S
        time.sleep(1.0)  # the device drops off the bus first; polling at once finds the old one
        while time.monotonic() < deadline and not self._closing.is_set():
            try:
                _find_device(self._serial)
                return
            except DeviceError:
                time.sleep(0.2)
        raise DeviceError(f"D435 {self._serial}: did not come back within {REENUMERATE_TIMEOUT_S} s")

    def _take(self, frames: Any) -> None:
        depth = frames.get_depth_frame()
        if not depth:
            return
        arrival = time.monotonic()
        for f in self._filters:
            depth = f.process(depth)
        pixels = np.asanyarray(depth.get_data()).copy()  # out of the SDK's 16-frame pool now
        vp = depth.profile.as_video_stream_profile()
        k = vp.get_intrinsics()
        frame = DepthFrame(
            depth=pixels,
            t=self._host_time(depth, arrival),
            frame_number=depth.get_frame_number(),
            intrinsics=DepthIntrinsics(k.width, k.height, k.fx, k.fy, k.ppx, k.ppy, self._depth_unit),
        )
        del depth, frames  # drop SDK references before the next frame
        if len(self._queue) >= QUEUE_LEN:
            self._queue.popleft()
            self.counts["queue_overflows"] += 1
        self._queue.append(frame)
        self.counts["frames"] += 1

    @staticmethod
    def _host_time(frame: Any, arrival: float) -> float:
        """Map the frame's stamp onto host monotonic seconds. In the global_time domain the stamp
        is host wall-clock ms at capture, so the capture latency is known; otherwise (no
        metadata) only the arrival time is."""
        if frame.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
            latency = time.time() - frame.get_timestamp() / 1000.0
            if 0.0 <= latency < 1.0:
                return arrival - latency
        return arrival
