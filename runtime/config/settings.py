"""The runtime config and the per-robot calibration file: schemas, loading, overrides.

Every key is declared once here with its unit, default and allowed range; the shipped
`runtime/config/default_config.yaml` and `calibration/spark_default.yaml` are renderings of these
schemas (a test keeps them equal), so documentation and validation cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from runtime.config.calibration import (
    CALIBRATION_TITLE,
    Calibration,
    CameraMount,
    OdometryCalibration,
)
from runtime.config.devices import BaseConfig, DepthConfig
from runtime.config.schema import (
    apply_override,
    build,
    load_yaml_file,
    render_documented,
    section,
    setting,
)
from runtime.control.config import ControlConfig
from runtime.errors import ConfigError
from runtime.odometry.ekf import OdometryFilterConfig
from runtime.perception.depth_points import PerceptionConfig
from runtime.perception.obstacle_memory import ObstacleMemoryConfig
from runtime.perception.tracking import TrackerConfig
from runtime.planning.dwa import DWAConfig
from runtime.planning.stall_recovery import RecoveryConfig
from runtime.policy.actor import PolicyConfig
from runtime.safety.certificate import ShieldConfig
from runtime.safety.limits import LimitsConfig

__all__ = [
    "CALIBRATION_TITLE", "Calibration", "CameraMount", "Config", "LimitsConfig", "LoadedConfig",
    "OdometryCalibration", "load_calibration", "load_config", "render_calibration",
    "render_config",
]

CONFIG_DIR = Path(__file__).resolve().parent
DEFAULT_CONFIG_PATH = CONFIG_DIR / "default_config.yaml"
DEFAULT_CALIBRATION_PATH = CONFIG_DIR.parents[1] / "calibration" / "spark_default.yaml"


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
class RecorderConfig:
    directory: str = setting(
        "", "where recordings go; empty = $LOGS_DIRECTORY/recordings when systemd gives the "
        "service a LogsDirectory (/var/log/safemove/recordings), else no recording")
    full_depth_every: int = setting(
        15, "a full depth frame every this many frames the world model reads (15: once a second"
        " at 15 fps); the decimated image it read is recorded for every one", "frames", min=1,
        max=10000)
    file_max_mb: float = setting(100.0, "a file is closed and a new one begun at this size", "MB",
                                 min=0.1, max=100000.0)
    file_max_s: float = setting(600.0, "a file is closed and a new one begun at this age", "s",
                                min=1.0, max=86400.0)
    total_max_mb: float = setting(
        2000.0, "all recordings together; the oldest files are deleted to stay under it", "MB",
        min=0.1, max=1000000.0)
    queue_cycles: int = setting(
        40, "cycles waiting for the writer; a cycle offered to a full queue is not recorded"
        " (counted)", "cycles", min=1, max=10000)


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
        RecoveryConfig, "stall recovery of the goal-driven jobs: step away from what blocks it, then go"
        " on; a frozen policy hands the drive to DWA")
    policy: PolicyConfig = section(PolicyConfig, "the TD3 actor (onnxruntime) of the safemove planner")
    limits: LimitsConfig = section(LimitsConfig, "velocity and acceleration limits, applied last")
    control: ControlConfig = section(
        ControlConfig, "the control socket: goals and missions for the service, and its status")
    recorder: RecorderConfig = section(
        RecorderConfig, "the flight recorder: every cycle to MCAP files (Foxglove opens them)")

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
