"""The per-robot calibration file's schema: camera extrinsics and wheel odometry constants.

Separate from the runtime config's schema because the pipeline stages that use calibration
(perception, odometry) are themselves config sections of it; this module imports neither.
"""

from __future__ import annotations

from dataclasses import dataclass

from runtime.config.schema import section, setting


@dataclass(frozen=True)
class CameraMount:
    translation_m: tuple[float, float, float] = setting(
        (0.094, 0.018, 0.643),
        "D435 camera_link origin in base_link (x forward, y left, z up); vendor URDF default",
        "m",
        min=-2.0,
        max=2.0,
    )
    rpy_deg: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0),
        "camera_link roll, pitch, yaw in base_link (pitch > 0 tilts the camera down)",
        "deg",
        min=-180.0,
        max=180.0,
    )


@dataclass(frozen=True)
class OdometryCalibration:
    m_per_tick: float = setting(
        0.00028885, "wheel travel per encoder tick", "m/tick", min=0.0, max=0.01, min_exclusive=True
    )
    axle_length_m: float = setting(
        0.266, "distance between the wheel contact points (URDF says 0.262)", "m", min=0.1, max=1.0
    )
    left_encoder_offset: int = setting(
        14,
        "byte offset of the physically left wheel's encoder in feedback frames; check by commanding"
        " omega > 0: the right wheel's count must rise faster and IMU yaw must increase",
        choices=(10, 14),
    )


@dataclass(frozen=True)
class Calibration:
    camera: CameraMount = section(CameraMount, "camera extrinsics (camera_link in base_link)")
    odometry: OdometryCalibration = section(OdometryCalibration, "wheel odometry constants")


CALIBRATION_TITLE = (
    "SafeMove per-robot calibration file.\n"
    "Defaults are the NXROBO Spark vendor values; run `safemove calibrate` to measure your robot."
)
