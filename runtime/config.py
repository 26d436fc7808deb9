"""The runtime config and the per-robot calibration file: schemas, loading, overrides.

Every key is declared once here with its unit, default and allowed range; the shipped
`runtime/default_config.yaml` and `calibration/spark_default.yaml` are renderings of these
schemas (a test keeps them equal), so documentation and validation cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from runtime.calibration_schema import (
    CALIBRATION_TITLE,
    Calibration,
    CameraMount,
    OdometryCalibration,
)
from runtime.dwa import DWAConfig
from runtime.errors import ConfigError
from runtime.limits import LimitsConfig
from runtime.obstacle_memory import ObstacleMemoryConfig
from runtime.odometry_ekf import OdometryFilterConfig
from runtime.perception import PerceptionConfig
from runtime.policy import PolicyConfig
from runtime.schema import (
    apply_override,
    build,
    load_yaml_file,
    render_documented,
    section,
    setting,
)
from runtime.shield import ShieldConfig
from runtime.stall_recovery import RecoveryConfig
from runtime.tracking import TrackerConfig

__all__ = [
    "CALIBRATION_TITLE", "Calibration", "CameraMount", "Config", "LimitsConfig", "LoadedConfig",
    "OdometryCalibration", "load_calibration", "load_config", "render_calibration",
    "render_config",
]

PACKAGE_DIR = Path(__file__).resolve().parent
DEFAULT_CONFIG_PATH = PACKAGE_DIR / "default_config.yaml"
DEFAULT_CALIBRATION_PATH = PACKAGE_DIR.parent / "calibration" / "spark_default.yaml"


# --- runtime config ------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoopConfig:
    control_hz: float = setting(20.0, "control loop rate", "Hz", min=1.0, max=200.0)
    feedback_max_age_s: float = setting(
        0.25,
        "base feedback older than this puts the loop in DEGRADED (brake to a stop)",
        "s",
        min=0.02,
        max=5.0,
    )
    startup_timeout_s: float = setting(
        5.0,
        "how long start-up waits for the first base feedback (and depth frame) before refusing"
        " to start",
        "s",
        min=0.5,
        max=120.0,
    )
    stats_interval_s: float = setting(
        10.0, "how often the loop logs its timing statistics (0 = never)", "s", min=0.0, max=3600.0
    )
    stop_on_cliff: bool = setting(
        True, "treat a cliff or wheel-drop report from the base as a hazard: brake and hold"
    )


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


@dataclass(frozen=True)
class RobotConfig:
    radius_m: float = setting(
        0.17, "radius of the disc that covers the robot's footprint (Spark: 0.17 m); the planner"
        " and the shield keep their margins outside it", "m", min=0.01, max=2.0)


@dataclass(frozen=True)
class Config:
    """The runtime config. Values two stages need are set once (`robot.radius_m`,
    `loop.control_hz`) and copied into the stages' sections here (schema.derived)."""

    calibration_file: str = setting(
        "",
        "per-robot calibration file; relative paths are relative to this config file;"
        " empty = the vendor defaults in calibration/spark_default.yaml",
    )
    robot: RobotConfig = section(RobotConfig, "the robot's body")
    loop: LoopConfig = section(LoopConfig, "control loop timing and health")
    base: BaseConfig = section(BaseConfig, "Spark base serial link")
    depth: DepthConfig = section(DepthConfig, "depth camera (RealSense D435) or its simulated stand-in")
    odometry: OdometryFilterConfig = section(
        OdometryFilterConfig, "odometry EKF: wheel increments fused with the IMU gyro"
    )
    perception: PerceptionConfig = section(
        PerceptionConfig, "depth → obstacle points and scan in base_link"
    )
    memory: ObstacleMemoryConfig = section(
        ObstacleMemoryConfig, "obstacle memory in odom: what left the camera's view"
    )
    tracking: TrackerConfig = section(TrackerConfig, "clusters → tracked people with velocity")
    dwa: DWAConfig = section(DWAConfig, "the fixed-budget Dynamic Window Approach")
    shield: ShieldConfig = section(ShieldConfig, "the safety shield that certifies every command")
    recovery: RecoveryConfig = section(
        RecoveryConfig, "the DWA job's stall recovery: step away from what blocks it, then go on")
    policy: PolicyConfig = section(PolicyConfig, "the TD3 actor (onnxruntime) of the safemove planner")
    limits: LimitsConfig = section(LimitsConfig, "velocity and acceleration limits, applied last")

    def __post_init__(self) -> None:
        period, radius = 1.0 / self.loop.control_hz, self.robot.radius_m
        object.__setattr__(self, "dwa", replace(self.dwa, robot_radius_m=radius,
                                                window_dt=period))
        object.__setattr__(self, "shield", replace(self.shield, robot_radius=radius,
                                                   period=period))


CONFIG_TITLE = (
    "SafeMove runtime configuration.\n"
    "Every key is optional; a missing key takes the default shown. Units are SI.\n"
    "Print the effective config with `safemove config show`; override with --set KEY=VALUE."
)


@dataclass(frozen=True)
class LoadedConfig:
    """The validated config, the calibration it refers to, and where each came from."""

    config: Config
    calibration: Calibration
    config_path: Path
    calibration_path: Path


def _resolve_calibration_path(config: Config, config_path: Path) -> Path:
    if not config.calibration_file:
        return DEFAULT_CALIBRATION_PATH
    path = Path(config.calibration_file).expanduser()
    return path if path.is_absolute() else config_path.parent / path


def load_calibration(path: Path) -> Calibration:
    """Load and validate a calibration file. An empty one is refused: it would silently give the
    vendor defaults, which is what a lost or truncated calibration looks like."""
    data = load_yaml_file(path, "calibration file")
    if data is None or data == {}:
        raise ConfigError(f"{path}: calibration file is empty; run `safemove calibrate`, or set"
                          " calibration_file to '' for the vendor defaults")
    return build(Calibration, data, str(path))


def load_config(path: Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> LoadedConfig:
    """Load, override and validate the config and its calibration; raises ConfigError (exit 2)."""
    config_path = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    data: Any = load_yaml_file(config_path, "config file")
    if data is None:
        data = {}
    source = str(config_path)
    if overrides and isinstance(data, dict):  # a non-mapping file is reported by build()
        for assignment in overrides:
            apply_override(data, Config, assignment)
        source += " (with --set " + ", ".join(overrides) + ")"
    config = build(Config, data, source)
    calibration_path = _resolve_calibration_path(config, config_path)
    calibration = load_calibration(calibration_path)
    return LoadedConfig(config, calibration, config_path, calibration_path)


def render_config(config: Config | None = None) -> str:
    """Documented YAML for a config (the defaults when None): the shipped file is this text."""
    return render_documented(config if config is not None else Config(), CONFIG_TITLE)


def render_calibration(calibration: Calibration | None = None) -> str:
    """Documented YAML for a calibration (the vendor defaults when None)."""
    return render_documented(
        calibration if calibration is not None else Calibration(), CALIBRATION_TITLE
    )
