"""The device sections of the config: the Spark base's serial link and the depth camera. The
drivers read only these (and the calibration), so importing a driver loads no pipeline stage."""

from __future__ import annotations

from dataclasses import dataclass

from runtime.config.schema import setting


@dataclass(frozen=True)
class BaseConfig:
    port: str = setting("/dev/sparkBase", "serial device of the Spark base (udev symlink)")
    baud: int = setting(115200, "serial baud rate", "baud", choices=(9600, 57600, 115200, 230400))
    resend_hz: float = setting(
        20.0, "rate at which the current wheel command is resent to the base", "Hz", min=1.0, max=100.0
    )
    command_timeout_s: float = setting(
        0.25,
        "the link sends stop when the loop has not fed a command for this long",
        "s",
        min=0.05,
        max=2.0,
    )
    query_retry_s: float = setting(
        1.0,
        "without feedback this long after connecting, send the well-formed query (then alternate)",
        "s",
        min=0.1,
        max=10.0,
    )
    reconnect_min_s: float = setting(
        0.1, "first wait before reopening a vanished port", "s", min=0.01, max=10.0
    )
    reconnect_max_s: float = setting(
        2.0, "longest wait between reopen attempts (exponential backoff)", "s", min=0.1, max=60.0
    )
    glitch_ticks: int = setting(
        20,
        "an encoder delta this far beyond what the wheel can travel in the frame's base-clock"
        " time (1.5 × max_wheel_speed_m_s) is a glitch: the frame is rejected (slack for count"
        " quantisation and jitter)",
        "ticks",
        min=10,
    )
    max_wheel_speed_m_s: float = setting(
        0.5, "per-wheel speed limit of the firmware (±500 mm/s)", "m/s", min=0.05, max=0.5
    )
    flag_debounce_frames: int = setting(
        2,
        "cliff and wheel-drop flags count only when this many accepted feedback frames in a row"
        " agree (set or clear), so one corrupted frame cannot stop or release the robot; each"
        " frame beyond the first adds one feedback period of latency (20 ms at 50 Hz)",
        "frames",
        min=1,
        max=10,
    )


@dataclass(frozen=True)
class DepthConfig:
    source: str = setting(
        "none",
        "where depth comes from: none, d435 (the live camera) or sim (the depth link of"
        " `safemove sim`)",
        choices=("none", "d435", "sim"),
    )
    max_age_s: float = setting(
        0.25, "depth older than this puts the loop in DEGRADED (brake to a stop)", "s",
        min=0.02, max=5.0,
    )
    max_future_s: float = setting(
        0.1,
        "a frame stamped further ahead of the host clock than this, or before the previous"
        " frame, is dropped and counted (a sensor clock jump); if good frames stop, depth goes"
        " stale", "s", min=0.0, max=5.0,
    )
    min_valid_fraction: float = setting(
        0.02,
        "a frame with fewer valid pixels than this fraction means the camera is blind (covered,"
        " dazzled, saturated, or a wall inside its minimum range): DEGRADED, the robot holds"
        " still until it sees again", min=0.0, max=1.0,
    )
    sim_socket: str = setting("", "Unix socket of `safemove sim`'s depth link (source: sim)")
    serial: str = setting("", "D435 serial number to open; empty = the only one connected")
    width: int = setting(848, "D435 depth width", "px", choices=(424, 480, 640, 848, 1280))
    height: int = setting(480, "D435 depth height", "px", choices=(240, 270, 360, 480, 720))
    fps: int = setting(30, "D435 depth frame rate", "Hz", choices=(6, 15, 30, 60, 90))
    decimation: int = setting(
        1, "D435 decimation filter magnitude (1 = off); first in the SDK's filter order",
        choices=(1, 2, 3, 4),
    )
    spatial_filter: bool = setting(
        False, "D435 spatial filter (run in disparity space, as the SDK recommends)"
    )
    temporal_filter: bool = setting(False, "D435 temporal filter (smears moving people)")
    hole_filling: bool = setting(False, "D435 hole filling (invents depth: off for safety)")
    frame_timeout_s: float = setting(
        1.0, "a D435 frame this late counts as a stall", "s", min=0.1, max=10.0
    )
    restart_after_stalls: int = setting(
        3, "stalls in a row before the D435 pipeline is restarted", min=1, max=100
    )
    reset_after_restarts: int = setting(
        2, "pipeline restarts in a row before a hardware reset of the D435", min=1, max=100
    )
