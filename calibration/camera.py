"""Camera extrinsics from frames of a still robot: the floor, and optionally a ChArUco board.

Pure: images and the previous mount in, the new mount and its evidence out. The command
(`calibration.cli`) gathers the frames and writes the file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.charuco import (
    BoardFit,
    BoardNotFoundError,
    BoardPlacement,
    BoardSpec,
    fit_mount_to_board,
    observe_board,
)
from calibration.floor_fit import FloorFit, FloorFitConfig, NoFloorError, fit_floor_frames
from runtime.config.calibration import CameraMount
from runtime.errors import UserError
from runtime.types import DepthIntrinsics

MAX_BOARD_RMS_PX = 3.0  # a worse fit means the board's pose or geometry was given wrong
BOARD_HEIGHT_WARN_M = 0.03  # the board and the floor disagree on the camera height by more


@dataclass(frozen=True)
class BoardInput:
    images: list[np.ndarray]
    intrinsics: DepthIntrinsics
    spec: BoardSpec
    placement: BoardPlacement


@dataclass(frozen=True)
class CameraResult:
    mount: CameraMount
    floor: FloorFit
    board: BoardFit | None

    def summary(self) -> dict:
        out = {
            "height_m": round(self.floor.height_m, 4),
            "pitch_deg": round(self.mount.rpy_deg[1], 3),
            "roll_deg": round(self.mount.rpy_deg[0], 3),
            "floor_inliers": self.floor.inliers,
            "floor_points": self.floor.points,
            "floor_rms_m": round(self.floor.rms_m, 5),
        }
        if self.board is not None:
            out.update(yaw_deg=round(self.mount.rpy_deg[2], 3),
                       x_m=round(self.mount.translation_m[0], 4),
                       y_m=round(self.mount.translation_m[1], 4),
                       board_rms_px=round(self.board.rms_px, 3),
                       board_height_m=round(self.board.free_height_m, 4))
        return out

    def warnings(self) -> list[str]:
        if self.board is None:
            return []
        gap = self.board.free_height_m - self.floor.height_m
        if abs(gap) <= BOARD_HEIGHT_WARN_M:
            return []
        return [(f"the board puts the camera {gap:+.3f} m off the floor's height: check the"
                 " board's measured height (--board-pose Z) and its square size")]


def calibrate_camera(depths: list[np.ndarray], intrinsics: DepthIntrinsics,
                     previous: CameraMount, board: BoardInput | None = None,
                     floor_config: FloorFitConfig | None = None) -> CameraResult:
    """Height, pitch, roll from the floor; x, y, yaw from the board when given, otherwise kept
    from `previous`. UserError (one line) when the floor or the board cannot be found."""
    try:
        floor = fit_floor_frames(depths, intrinsics, previous, floor_config)
    except NoFloorError as exc:
        raise UserError(f"no floor in view ({exc}): point the camera at open floor, at least"
                        " a metre of it, and keep people and clutter out") from None
    mount = floor.mount(previous)
    if board is None:
        return CameraResult(mount, floor, None)
    try:
        obs = observe_board(board.images, board.spec)
        fit = fit_mount_to_board(obs, board.spec, board.placement, board.intrinsics, mount)
    except (BoardNotFoundError, ValueError) as exc:
        raise UserError(f"board: {exc}") from None
    if fit.rms_px > MAX_BOARD_RMS_PX:
        raise UserError(
            f"board: the corners miss the given board pose by {fit.rms_px:.1f} px RMS (more"
            f" than {MAX_BOARD_RMS_PX:g}): check --board-pose and the board's geometry")
    return CameraResult(fit.mount, floor, fit)
