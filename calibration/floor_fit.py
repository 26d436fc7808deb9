"""Floor plane from depth: RANSAC with a near-vertical normal prior, then an SVD refit.

Pure (numpy in, dataclasses out). Everything happens in the camera optical frame (z forward,
x right, y down), so no calibration is assumed except for the prior "up" direction: RANSAC
returns the largest plane, which may be a wall, so only planes whose normal lies within
`max_tilt_deg` of the prior up and that pass below the camera are considered (field notes).

From the fitted plane n·p + d = 0 (n oriented towards the camera, so d > 0 is the camera's
height above the floor) come the camera's height, pitch and roll. Yaw and the horizontal
offsets are not observable from the floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.config.calibration import CameraMount
from runtime.geometry import R_LINK_OPTICAL, rpy_matrix
from runtime.types import DepthIntrinsics


@dataclass(frozen=True)
class FloorFitConfig:
    """Knobs of the fit; the defaults suit a D435 at 848x480 looking at an indoor floor."""

    max_tilt_deg: float = 30.0  # prior: floor normal within this of the prior up direction
    min_height_m: float = 0.05  # the camera is at least this far above any floor candidate
    max_range_m: float = 10.0  # points farther than this (Z) are not used
    stride: int = 4  # every n-th pixel in both directions per frame
    ransac_iters: int = 1000
    ransac_reach: int = 30  # RANSAC triples: points within this many grid cells of an anchor
    ransac_sample: int = 4000  # points scored per hypothesis
    inlier_m: float = 0.03  # RANSAC inlier distance
    refit_rounds: int = 3  # SVD refits, each on the inliers of the previous plane
    refit_sigmas: float = 3.0  # refit inliers: within this many robust sigmas (at least 5 mm)
    min_inliers: int = 300  # fewer floor points (grid cells) than this: no floor in view
    min_inlier_share: float = 0.02  # ... or less than this share of the valid points
    seed: int = 0


@dataclass(frozen=True)
class FloorFit:
    """The floor in the optical frame: unit normal towards the camera and the camera height."""

    normal: np.ndarray  # (3,) optical frame, points from the floor towards the camera
    height_m: float  # plane offset d: the camera's distance above the floor
    inliers: int
    points: int  # candidate points the fit saw
    rms_m: float  # RMS distance of the inliers to the plane

    def camera_pitch_roll_deg(self) -> tuple[float, float]:
        """camera_link pitch and roll (ROS fixed axis, pitch > 0 tilts down) that put this floor
        under the camera: the floor normal in camera_link is (−sin p, cos p sin r, cos p cos r)
        whatever the yaw, because R = Rz(y) Ry(p) Rx(r) and Rz leaves the up axis alone."""
        n = R_LINK_OPTICAL @ self.normal
        pitch = math.degrees(math.asin(max(-1.0, min(1.0, -float(n[0])))))
        roll = math.degrees(math.atan2(float(n[1]), float(n[2])))
        return pitch, roll

    def mount(self, previous: CameraMount) -> CameraMount:
        """`previous` with height, pitch and roll from the floor; x, y and yaw kept (the floor
        does not observe them). base_link lies on the floor, so translation z is the height."""
        pitch, roll = self.camera_pitch_roll_deg()
        x, y, _ = previous.translation_m
        return CameraMount((x, y, self.height_m), (roll, pitch, previous.rpy_deg[2]))


class NoFloorError(ValueError):
    """No plane that could be the floor was found; the message says what was seen."""


def up_in_optical(mount: CameraMount) -> np.ndarray:
    """The floor normal (base_link +z) in the optical frame of a camera mounted as `mount`."""
    r_base_optical = rpy_matrix(*(math.radians(a) for a in mount.rpy_deg)) @ R_LINK_OPTICAL
    return r_base_optical.T @ np.array([0.0, 0.0, 1.0])


def mean_depth_grid(depths: list[np.ndarray], intrinsics: DepthIntrinsics, stride: int,
                    max_range_m: float, min_valid_share: float = 0.5) -> np.ndarray:
    """(H', W', 3) optical-frame points of the per-pixel mean depth over frames of a still
    camera, on a `stride` grid; NaN where fewer than `min_valid_share` of the frames had depth
    (edge dropout, the blind zone) or beyond `max_range_m`. Averaging first cuts the noise by
    the square root of the frame count and keeps the image structure RANSAC samples from."""
    k = intrinsics
    stack = np.stack([d[::stride, ::stride] for d in depths]).astype(np.float64)
    valid = stack > 0
    count = valid.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = stack.sum(axis=0) * k.depth_unit_m / count
    z[(count < max(1.0, min_valid_share * len(depths))) | (z > max_range_m)] = np.nan
    v, u = np.mgrid[0:k.height:stride, 0:k.width:stride]
    return np.stack(((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z), axis=-1)


def _plane_svd(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total least squares plane through points: (unit normal, offset) with n·p + d = 0."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    n = vt[2]
    return n, -float(n @ centre)


def _local_triples(grid: np.ndarray, count: int, reach: int,
                   rng: np.random.Generator) -> np.ndarray:
    """(k, 3, 3) point triples, each an anchor and two points within `reach` grid cells of it.
    The floor is one connected region of the image: a triple drawn near a floor anchor is
    likely all floor, where three points drawn anywhere rarely are when the floor fills a
    tenth of the view (a camera pitched up sees it only in its lowest rows)."""
    h, w, _ = grid.shape
    valid = np.flatnonzero(np.isfinite(grid[..., 2]).ravel())
    anchors = valid[rng.integers(0, len(valid), size=count)]
    av, au = np.divmod(anchors, w)
    off = rng.integers(-reach, reach + 1, size=(count, 2, 2))
    vs = np.clip(av[:, None] + off[..., 0], 0, h - 1)
    us = np.clip(au[:, None] + off[..., 1], 0, w - 1)
    flat = grid.reshape(-1, 3)
    triples = np.concatenate((flat[anchors][:, None], flat[vs * w + us]), axis=1)
    return triples[np.isfinite(triples).all(axis=(1, 2))]


def fit_floor(grid: np.ndarray, up_prior: np.ndarray,
              config: FloorFitConfig | None = None) -> FloorFit:
    """Fit the floor to an (H', W', 3) optical-frame point grid (NaN = no depth);
    NoFloorError when nothing floor-like is there."""
    cfg = config if config is not None else FloorFitConfig()
    points = grid.reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    n_pts = len(points)
    if n_pts < max(3, cfg.min_inliers):
        raise NoFloorError(f"only {n_pts} valid depth points (need {cfg.min_inliers})")
    up = np.asarray(up_prior, dtype=float)
    up = up / np.linalg.norm(up)
    rng = np.random.default_rng(cfg.seed)
    scored = points[rng.choice(n_pts, min(n_pts, cfg.ransac_sample), replace=False)]
    tri = _local_triples(grid, cfg.ransac_iters, cfg.ransac_reach, rng)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 1e-9
    normals, tri = normals[keep] / lengths[keep, None], tri[keep]
    normals[normals @ up < 0] *= -1.0  # orient every hypothesis "up", towards the camera
    offsets = -np.einsum("ij,ij->i", normals, tri[:, 0])
    plausible = (normals @ up >= math.cos(math.radians(cfg.max_tilt_deg))) & (
        offsets >= cfg.min_height_m)
    if not plausible.any():
        raise NoFloorError(f"no plane within {cfg.max_tilt_deg:g} deg of level below the camera"
                           f" among {n_pts} points")
    normals, offsets = normals[plausible], offsets[plausible]
    # Score: support minus points below the plane. Nothing real lies under the floor, while a
    # box top or a plane cutting through clutter has the floor itself below it.
    signed = scored @ normals.T + offsets
    score = (np.abs(signed) <= cfg.inlier_m).sum(axis=0) - (
        signed < -2.0 * cfg.inlier_m).sum(axis=0)
    best = int(np.argmax(score))
    n, d = normals[best], float(offsets[best])
    inliers = points[np.abs(points @ n + d) <= cfg.inlier_m]
    for _ in range(cfg.refit_rounds):
        if len(inliers) < 3:
            break
        n, d = _plane_svd(inliers)
        if n @ up < 0:
            n, d = -n, -d
        dist = np.abs(points @ n + d)
        resid = dist[dist <= cfg.inlier_m]
        sigma = 1.4826 * float(np.median(resid)) if len(resid) else cfg.inlier_m
        inliers = points[dist <= max(0.005, cfg.refit_sigmas * sigma)]
    count = len(inliers)
    if count < cfg.min_inliers or count < cfg.min_inlier_share * n_pts:
        raise NoFloorError(f"the best level plane has {count} of {n_pts} points (need"
                           f" {cfg.min_inliers} and {cfg.min_inlier_share:.0%})")
    n, d = _plane_svd(inliers)
    if n @ up < 0:
        n, d = -n, -d
    tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(n @ up)))))
    if tilt > cfg.max_tilt_deg or d < cfg.min_height_m:
        raise NoFloorError(f"the refitted plane is {tilt:.1f} deg off level, {d:.3f} m below"
                           " the camera: not a floor")
    rms = float(np.sqrt(np.mean((inliers @ n + d) ** 2)))
    return FloorFit(n, d, count, n_pts, rms)


def fit_floor_frames(depths: list[np.ndarray], intrinsics: DepthIntrinsics,
                     prior: CameraMount, config: FloorFitConfig | None = None) -> FloorFit:
    """The floor seen by a still camera over many frames; `prior` gives the up direction."""
    cfg = config if config is not None else FloorFitConfig()
    if not depths:
        raise NoFloorError("no depth frames")
    grid = mean_depth_grid(depths, intrinsics, cfg.stride, cfg.max_range_m)
    return fit_floor(grid, up_in_optical(prior), cfg)
