"""A quick health check of the current calibration against live or recorded data.

Pure: frames or run totals and the calibration in, a pass/fail item per check out.
- floor height and tilt: the floor fitted afresh vs the floor the calibration implies;
- below the floor: the share of depth points the calibration puts under the floor (a wrong
  pitch or height shows up here first, and perception would call those points free space);
- encoder mapping: in a commanded left turn the calibrated right wheel must advance, the left
  go back, and the IMU yaw rise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.floor_fit import (
    FloorFitConfig,
    NoFloorError,
    fit_floor,
    mean_depth_grid,
    up_in_optical,
)
from calibration.odometry_fit import RunTotals
from runtime.config.calibration import CameraMount, OdometryCalibration
from runtime.geometry import R_LINK_OPTICAL, rpy_matrix
from runtime.types import DepthIntrinsics


@dataclass(frozen=True)
class CheckLimits:
    height_m: float = 0.02
    tilt_deg: float = 1.0
    below_m: float = 0.03  # a point this far under the calibrated floor counts as below it
    below_share: float = 0.01


@dataclass(frozen=True)
class CheckItem:
    name: str
    ok: bool | None  # None: could not be checked
    value: float | None
    limit: float | None
    detail: str

    def line(self) -> str:
        verdict = {True: "PASS", False: "FAIL", None: "SKIP"}[self.ok]
        return f"{verdict}  {self.name}: {self.detail}"

    def as_dict(self) -> dict:
        return {"name": self.name, "ok": self.ok,
                "value": None if self.value is None else round(self.value, 6),
                "limit": self.limit, "detail": self.detail}


def check_camera(depths: list[np.ndarray], intrinsics: DepthIntrinsics, mount: CameraMount,
                 limits: CheckLimits | None = None,
                 floor_config: FloorFitConfig | None = None) -> list[CheckItem]:
    """Floor height, floor tilt and the share of points below the floor, for frames of a still
    camera on a robot standing on level floor."""
    lim = limits if limits is not None else CheckLimits()
    cfg = floor_config if floor_config is not None else FloorFitConfig()
    grid = mean_depth_grid(depths, intrinsics, cfg.stride, cfg.max_range_m)
    r_base_optical = rpy_matrix(*(math.radians(a) for a in mount.rpy_deg)) @ R_LINK_OPTICAL
    pts = grid.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    z = pts @ r_base_optical[2] + mount.translation_m[2]
    share = float(np.mean(z < -lim.below_m)) if len(z) else math.nan
    below = CheckItem(
        "below_floor", bool(share <= lim.below_share) if len(z) else None, share,
        lim.below_share,
        f"{share:.2%} of {len(z)} depth points lie more than {lim.below_m * 100:g} cm under the"
        f" calibrated floor (limit {lim.below_share:.0%})" if len(z) else "no depth points")
    try:
        fit = fit_floor(grid, up_in_optical(mount), cfg)
    except NoFloorError as exc:
        skipped = f"no floor in view ({exc})"
        return [CheckItem("floor_height", None, None, lim.height_m, skipped),
                CheckItem("floor_tilt", None, None, lim.tilt_deg, skipped), below]
    dz = fit.height_m - mount.translation_m[2]
    tilt = math.degrees(math.acos(min(1.0, float(fit.normal @ up_in_optical(mount)))))
    return [
        CheckItem("floor_height", abs(dz) <= lim.height_m, dz, lim.height_m,
                  f"the floor is {dz * 100:+.1f} cm from where the calibration puts it (limit"
                  f" {lim.height_m * 100:g} cm; fit RMS {fit.rms_m * 1000:.1f} mm over"
                  f" {fit.inliers} points)"),
        CheckItem("floor_tilt", tilt <= lim.tilt_deg, tilt, lim.tilt_deg,
                  f"the floor is tilted {tilt:.2f} deg against the calibration (limit"
                  f" {lim.tilt_deg:g} deg)"),
        below,
    ]


def check_mapping(turn_left: RunTotals, calibration: OdometryCalibration) -> CheckItem:
    """The calibrated left/right mapping against a commanded left turn in place."""
    left, right = turn_left.wheels(calibration.left_encoder_offset)
    imu = turn_left.imu_yaw_rad
    imu_txt = "no IMU" if imu is None else f"IMU yaw {math.degrees(imu):+.1f} deg"
    ok = right > 0 > left and (imu is None or imu > 0)
    hint = "" if ok else (
        "; the mapping is swapped: set odometry.left_encoder_offset to"
        f" {24 - calibration.left_encoder_offset}" if left > 0 > right and (imu is None or imu > 0)
        else "; run `safemove calibrate odometry`")
    return CheckItem("encoder_mapping", ok, None, None,
                     f"left turn: calibrated left wheel {left:+d} ticks, right {right:+d},"
                     f" {imu_txt}{hint}")
