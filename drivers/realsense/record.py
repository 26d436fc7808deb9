"""Write a real pyrealsense2 recording (rosbag2 .db3) from depth frames we push ourselves.

A `rs.software_device` with one Z16 depth stream (intrinsics set by hand, read-only
depth_units option) is wrapped in an uncompressed `rs.recorder`; each `write()` pushes one
`rs.software_video_frame`. `close()` stops the sensor and drops the recorder, the sensor and the
device in that order, which is what makes the SDK finish the file.
"""

from __future__ import annotations

import os

import numpy as np
import pyrealsense2 as rs

from drivers.depth_source import DepthIntrinsics
from runtime.errors import UserError


class DepthRecorder:
    def __init__(self, path: str | os.PathLike, intrinsics: DepthIntrinsics, fps: int = 30) -> None:
        self.path = os.fspath(path)
        if not self.path.endswith(".db3"):
            raise UserError(f"{self.path}: recording must be a .db3 file (rosbag2), not "
                            f"{os.path.splitext(self.path)[1] or 'no extension'}")
        parent = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(parent):
            raise UserError(f"{self.path}: folder {parent} does not exist")
        self.intrinsics = intrinsics
        k = intrinsics
        intr = rs.intrinsics()
        intr.width, intr.height = k.width, k.height
        intr.fx, intr.fy, intr.ppx, intr.ppy = k.fx, k.fy, k.cx, k.cy
        intr.model = rs.distortion.brown_conrady  # what a D435 reports, all coefficients 0
        intr.coeffs = [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
        vs.width, vs.height, vs.fps, vs.bpp = k.width, k.height, int(fps), 2
        vs.fmt, vs.intrinsics = rs.format.z16, intr
        self._dev = rs.software_device()
        self._sensor = self._dev.add_sensor("Depth")
        self._profile = self._sensor.add_video_stream(vs).as_video_stream_profile()
        self._sensor.add_read_only_option(rs.option.depth_units, float(k.depth_unit_m))
        try:
            self._recorder = rs.recorder(self.path, self._dev, False)  # False: no compression
        except RuntimeError as e:
            raise UserError(f"{self.path}: cannot record: {e}") from None
        self._sensor.open(self._profile)
        self._queue = rs.frame_queue(1)  # the sensor needs a consumer; the recorder taps before it
        self._sensor.start(self._queue)
        self._open = True
        self.frames_written = 0

    def write(self, depth: np.ndarray, t_ms: float, frame_number: int) -> None:
        """Push one HxW uint16 depth image stamped t_ms (milliseconds) as frame `frame_number`."""
        if not self._open:
            raise RuntimeError("DepthRecorder is closed")
        k = self.intrinsics
        if depth.dtype != np.uint16 or depth.shape != (k.height, k.width):
            raise ValueError(f"depth must be uint16 {(k.height, k.width)}, got {depth.dtype} "
                             f"{depth.shape}")
        f = rs.software_video_frame()
        f.pixels = np.ascontiguousarray(depth)
        f.stride = k.width * 2
        f.bpp = 2
        f.timestamp = float(t_ms)
        f.domain = rs.timestamp_domain.hardware_clock
        f.frame_number = int(frame_number)
        f.profile = self._profile
        self._sensor.on_video_frame(f)
        self.frames_written += 1
        while self._queue.poll_for_frame():  # keep the consumer side empty
            pass

    def close(self) -> None:
        """Stop streaming and finish the file (idempotent)."""
        if not self._open:
            return
        self._open = False
        self._sensor.stop()
        self._sensor.close()
        del self._recorder  # the recorder writes the file's tail when it is destroyed
        del self._queue, self._profile, self._sensor, self._dev

    def __enter__(self) -> DepthRecorder:  # noqa: PYI034 - Python 3.10 has no typing.Self
        return self

    def __exit__(self, *exc) -> None:
        self.close()
