"""Camera yaw and horizontal offset from a ChArUco board standing at a known pose.

The floor fixes the camera's height, pitch and roll but not where it looks in the horizontal
plane; a board whose pose in base_link the user has measured does. Detection uses OpenCV's
object API (`CharucoDetector.detectBoard`, `matchImagePoints`, `solvePnP`: the old free
functions are gone from current wheels, field notes) on the left infrared image, which is the
depth frame, so the depth intrinsics apply.

Board frame (OpenCV's): origin at the pattern's top-left outer corner as printed, x to the
right, y down, z into the board. A board at yaw 0 stands upright and faces the robot squarely:
its x is base −y, its y is base −z and its z is base +x. Its pose is given by the pattern's
centre (x, y, z in base_link) and its yaw about the vertical.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from runtime.config.calibration import CameraMount
from runtime.geometry import R_LINK_OPTICAL, rpy_matrix
from runtime.types import DepthIntrinsics

MIN_CORNERS = 6  # ChArUco corners per frame for a pose (solvePnP needs 4; a few more for noise)


@dataclass(frozen=True)
class BoardSpec:
    """A printed ChArUco board. Default: 7x5 squares of 55 mm (fits A3), 4x4 markers."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.055
    marker_m: float = 0.041
    dictionary: str = "DICT_4X4_50"

    def board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board; ValueError naming the problem for an impossible spec."""
        if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")
        if not 0 < self.marker_m < self.square_m:
            raise ValueError(f"marker size {self.marker_m} m must be between 0 and the square"
                             f" size {self.square_m} m")
        if self.squares_x < 2 or self.squares_y < 2:
            raise ValueError("a ChArUco board needs at least 2x2 squares")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        markers = (self.squares_x * self.squares_y) // 2
        if markers > dictionary.bytesList.shape[0]:
            raise ValueError(f"{self.dictionary} has {dictionary.bytesList.shape[0]} markers, the"
                             f" board needs {markers}")
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m,
                                      self.marker_m, dictionary)

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_m, self.squares_y * self.square_m


@dataclass(frozen=True)
class BoardPlacement:
    """Where the user put the board: pattern centre in base_link (m) and yaw (deg, 0 = facing
    the robot squarely, positive = turned counter-clockwise seen from above)."""

    x: float
    y: float
    z: float
    yaw_deg: float

    def pose_in_base(self, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
        """(R_base_board, board origin in base_link)."""
        r = rpy_matrix(0.0, 0.0, math.radians(self.yaw_deg)) @ R_LINK_OPTICAL
        w, h = spec.size_m
        origin = np.array([self.x, self.y, self.z]) - r @ np.array([w / 2, h / 2, 0.0])
        return r, origin


@dataclass(frozen=True)
class BoardObservation:
    """Matched board corners over the frames that showed the board."""

    object_points: np.ndarray  # (N, 3) board frame, m
    image_points: np.ndarray  # (N, 2) px
    frames_used: int
    frames_seen: int


class BoardNotFoundError(ValueError):
    """Too few frames showed enough of the board."""


def observe_board(images: list[np.ndarray], spec: BoardSpec, min_frames: int = 3
                  ) -> BoardObservation:
    """Detect the board in each 8-bit infrared image and pool the matched corners."""
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    obj, img = [], []
    for image in images:
        corners, ids, _, _ = detector.detectBoard(image)
        if ids is None or len(ids) < MIN_CORNERS:
            continue
        o, i = board.matchImagePoints(corners, ids)
        obj.append(o.reshape(-1, 3))
        img.append(i.reshape(-1, 2))
    if len(obj) < min_frames:
        raise BoardNotFoundError(
            f"the board ({spec.squares_x}x{spec.squares_y} squares, {spec.dictionary}) was found"
            f" in {len(obj)} of {len(images)} infrared frames (need {min_frames} with at least"
            f" {MIN_CORNERS} corners)")
    return BoardObservation(np.concatenate(obj).astype(np.float64),
                            np.concatenate(img).astype(np.float64), len(obj), len(images))


def _camera_matrix(k: DepthIntrinsics) -> np.ndarray:
    return np.array([[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class BoardFit:
    """The camera mount that explains the board, and how well it does."""

    mount: CameraMount
    rms_px: float  # reprojection RMS of the constrained fit
    free_rms_px: float  # reprojection RMS of an unconstrained PnP (a check on the floor fit)
    free_height_m: float  # camera height the board alone implies (vs the floor's)


def fit_mount_to_board(obs: BoardObservation, spec: BoardSpec, placement: BoardPlacement,
                       intrinsics: DepthIntrinsics, floor_mount: CameraMount) -> BoardFit:
    """Camera x, y and yaw from the board, with z, roll and pitch held at the floor's values.

    A free PnP starts it (and is reported as a check); then only x, y and yaw are refined by
    least squares on the reprojection error: a frontal board couples yaw with sideways offset,
    and fixing the three values the floor measures better keeps that coupling out.
    """
    k = _camera_matrix(intrinsics)
    dist = np.zeros(5)
    ok, rvec, tvec = cv2.solvePnP(obs.object_points, obs.image_points, k, dist,
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise BoardNotFoundError("solvePnP found no pose for the board corners")
    rvec, tvec = cv2.solvePnPRefineLM(obs.object_points, obs.image_points, k, dist, rvec, tvec)
    r_board_base, origin = placement.pose_in_base(spec)
    r_cam_board = cv2.Rodrigues(rvec)[0]
    free_proj, _ = cv2.projectPoints(obs.object_points, rvec, tvec, k, dist)
    free_rms = float(np.sqrt(np.mean(np.sum((free_proj.reshape(-1, 2) - obs.image_points) ** 2,
                                            axis=1))))
    r_base_link = r_board_base @ r_cam_board.T @ R_LINK_OPTICAL.T
    cam_in_base = origin + r_board_base @ (-r_cam_board.T @ tvec.ravel())
    yaw0 = math.atan2(r_base_link[1, 0], r_base_link[0, 0])
    roll, pitch = (math.radians(a) for a in floor_mount.rpy_deg[:2])
    z = floor_mount.translation_m[2]
    pts_base = origin + obs.object_points @ r_board_base.T

    def residual(q: np.ndarray) -> np.ndarray:
        r_base_optical = rpy_matrix(roll, pitch, q[2]) @ R_LINK_OPTICAL
        p = (pts_base - np.array([q[0], q[1], z])) @ r_base_optical
        u = k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2]
        v = k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]
        return np.concatenate((u - obs.image_points[:, 0], v - obs.image_points[:, 1]))

    sol = least_squares(residual, np.array([cam_in_base[0], cam_in_base[1], yaw0]),
                        x_scale=np.array([0.01, 0.01, 0.01]))
    rms = float(np.sqrt(np.mean(sol.fun.reshape(2, -1) ** 2) * 2))
    x, y, yaw = sol.x
    mount = CameraMount((float(x), float(y), z),
                        (floor_mount.rpy_deg[0], floor_mount.rpy_deg[1], math.degrees(yaw)))
    return BoardFit(mount, rms, free_rms, float(cam_in_base[2]))
