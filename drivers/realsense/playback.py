"""DepthSource that replays a pyrealsense2 recording (.db3, or a legacy ROS 1 .bag).

Uses the real `rs.pipeline` with `enable_device_from_file(path, repeat_playback=False)`. The
playback device is put into non-real-time mode *before* the pipeline starts (via
`config.resolve`): set after `start()`, the first frames are already read in real time and the
pipeline's one-frame queue drops them. In non-real-time mode the reader waits for us, so no
frame is skipped however slowly we poll. The recorded timestamps (ms) are the clock (s).
End of file is `at_end` (playback status stopped and nothing left), never a stall. Right after
`start()` the status can still read `stopped` before playback begins (seen in 4 of 30 starts), so
the end only counts once playback has been seen running, or after a grace period for a
recording with no frames at all.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pyrealsense2 as rs

from drivers.depth_source import DepthFrame, DepthIntrinsics
from runtime.errors import UserError

START_GRACE_S = 3.0  # a recording that has not started playing by then has no frames
DRAIN_LIMIT_S = 30.0  # stop() reads what is left of a recording for at most this long


class PlaybackDepthSource:
    """Replays the depth stream of a recording; poll() never waits more than `poll_timeout_ms`."""

    def __init__(self, path: str | os.PathLike, poll_timeout_ms: int = 2) -> None:
        self.path = os.fspath(path)
        self.poll_timeout_ms = int(poll_timeout_ms)
        self.intrinsics: DepthIntrinsics | None = None
        self._pipe: rs.pipeline | None = None
        self._playback: rs.playback | None = None
        self._at_end = False
        self._seen_playing = False
        self._started_at = 0.0
        self.frames_delivered = 0

    def start(self) -> None:
        if not os.path.isfile(self.path):
            raise UserError(f"{self.path}: recording not found")
        pipe = rs.pipeline()
        cfg = rs.config()
        try:
            cfg.enable_device_from_file(self.path, repeat_playback=False)
            cfg.enable_stream(rs.stream.depth)
            cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(False)
            profile = pipe.start(cfg)
        except RuntimeError as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise UserError(f"{self.path}: not a readable RealSense recording ({msg})") from None
        try:
            playback = profile.get_device().as_playback()
            playback.set_real_time(False)
            vsp = profile.get_stream(rs.stream.depth).as_video_stream_profile()
            i = vsp.get_intrinsics()
            scale = profile.get_device().first_depth_sensor().get_depth_scale()
        except RuntimeError as e:
            pipe.stop()
            raise UserError(f"{self.path}: recording has no usable depth stream ({e})") from None
        self.intrinsics = DepthIntrinsics(
            width=i.width, height=i.height, fx=i.fx, fy=i.fy, cx=i.ppx, cy=i.ppy,
            depth_unit_m=float(scale),
        )
        self._pipe, self._playback, self._at_end = pipe, playback, False
        self._seen_playing = False
        self._started_at = time.monotonic()

    def _try_frame(self, timeout_ms: int) -> DepthFrame | None:
        pipe, intrinsics = self._pipe, self.intrinsics
        if pipe is None or intrinsics is None:  # stopped, or never started
            return None
        ok, frames = pipe.try_wait_for_frames(timeout_ms)
        if not ok:
            return None
        df = frames.get_depth_frame()
        if not df:
            return None
        depth = np.asanyarray(df.get_data()).copy()
        frame = DepthFrame(depth=depth, t=df.get_timestamp() / 1000.0,
                           frame_number=int(df.get_frame_number()), intrinsics=intrinsics)
        del df, frames
        self.frames_delivered += 1
        return frame

    def poll(self) -> DepthFrame | None:
        playback = self._playback  # set together with _pipe by start(), cleared by stop()
        if self._pipe is None or playback is None or self._at_end:
            return None
        frame = self._try_frame(self.poll_timeout_ms)
        if frame is not None:
            self._seen_playing = True
            return frame
        if self._finished(playback):
            # the reader has finished; take anything still in flight before calling it the end
            frame = self._try_frame(self.poll_timeout_ms)
            if frame is None:
                self._at_end = True
            return frame
        return None

    def _finished(self, playback: rs.playback) -> bool:
        """Whether playback has stopped at the end, not yet to begin (see the module docs)."""
        status = playback.current_status()
        if status == rs.playback_status.playing:
            self._seen_playing = True
            return False
        return status == rs.playback_status.stopped and (
            self._seen_playing or time.monotonic() - self._started_at > START_GRACE_S)

    @property
    def at_end(self) -> bool:
        return self._at_end

    def stop(self) -> None:
        """Stops the pipeline, after reading the rest of the recording: librealsense (2.59.1)
        can crash the process when a non-real-time playback is stopped mid-file (a segfault in
        `pipeline.stop()`: 2 of 5 runs of 50 such stops here), never once it has played to the
        end (0 of 300 stops)."""
        if self._pipe is not None:
            try:
                self._play_out(self._pipe, self._playback)
                self._pipe.stop()
            except RuntimeError:
                pass
            self._pipe = None
            self._playback = None

    def _play_out(self, pipe: rs.pipeline, playback: rs.playback | None) -> None:
        """Reads and drops the frames left until playback ends (at most DRAIN_LIMIT_S)."""
        give_up = time.monotonic() + DRAIN_LIMIT_S
        while playback is not None and not self._at_end and time.monotonic() < give_up:
            ok, _ = pipe.try_wait_for_frames(self.poll_timeout_ms)
            if ok:
                self._seen_playing = True
            elif self._finished(playback):
                self._at_end = True
