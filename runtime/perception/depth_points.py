"""Perception stage: one D435 depth image -> obstacle points and a bearing scan in base_link.

Model: pointcloud_to_laserscan with a base-frame transform (field notes, "Depth to obstacles").
Every (decimated) pixel is deprojected with a ray precomputed once from the intrinsics and the
camera mount, so a frame costs `Z * ray + t` per pixel: no per-frame rotation, no trigonometry on
the full image. Points inside a height band above the floor and inside `range_max_m` are
obstacles; they are binned by bearing and the minimum range per bin forms the scan.

Conventions (all base_link, REP 103: x forward, y left, z up, origin on the floor):
- bearing = atan2(y, x) of the point; bins run RIGHT TO LEFT (counter-clockwise, like a ROS
  LaserScan from angle_min to angle_max): bin 0 starts at `-bearing_span/2` (right), the last bin
  ends at `+bearing_span/2` (left). `bin_angles` are the bin centres in rad.
- range = hypot(x, y) from the base_link origin (not from the camera).
- `scan[b]` = minimum range of obstacle points in bin b; `inf` where the bin has no obstacle point.
  `inf` alone does NOT mean free: read it together with `unknown` and `free_range`.
- `unknown[b]` is True where the bin saw nothing usable: no valid depth at all (0, nearer than
  `min_range_m` or farther than `max_depth_m`, e.g. saturated), or a large part
  of the pixels that must see the floor at calibration returned no valid depth. A D435 returns 0
  both for "nothing within range" and for "closer than the minimum range" (blind zone), and both
  look alike in one frame; an obstacle closer than `min_range_m` blanks the floor behind it, so
  the floor test catches it. SAFE CHOICE: consumers (planner, shield) treat an unknown bin as
  OCCUPIED at `blind_range[b]` (the base_link range of the camera's minimum range in that
  bearing), never as free. `blind[b]` marks the unknown bins flagged by the missing-floor test.
- `free_range[b]` = how far the bin was seen to be free: the largest horizontal range of any valid
  return in the bin (floor included; range |camera offset + ray| bounded from below, so never
  overstated), capped by `scan[b]` and `range_max_m`; 0 for unknown bins. Obstacle memory clears
  remembered points only in front of it.
- Height band: a point is an obstacle when z_min_m + r * tan(floor_tilt_margin_deg) <= z <=
  z_max_m (z in base_link, r its horizontal distance from the camera), folded into one precomputed
  per-pixel coefficient so it costs one multiply and one compare per pixel. Default 5 cm + 1.25
  deg: with the camera 1 deg / 1 cm off calibration (worst sign) the floor still stays >= 5 cm
  below the threshold at every range in the simulator (1,000 noisy frames, tests).

Purity: no clock, no I/O. All per-pixel work goes into buffers preallocated in `__init__`
(float32, `out=`); the only per-frame allocations are proportional to the number of obstacle
points (index selection) and the tiny per-bin arrays. The output's arrays are views of internal
buffers, valid until the next `process()` call: copy what you keep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.config.calibration import CameraMount
from runtime.config.schema import setting
from runtime.geometry import R_LINK_OPTICAL, bin_index, rpy_matrix
from runtime.types import DepthIntrinsics

F32 = np.float32

@dataclass(frozen=True)
class FloorVerdict:
    """Is the floor where the calibration says? ok is None when too few floor points were seen."""

    ok: bool | None
    tilt_deg: float
    height_m: float
    points: int


@dataclass(frozen=True)
class PerceptionConfig:
    decimation: int = setting(
        4,
        "use every n-th pixel in both directions (1 = full 848x480); 4 keeps the world model"
        " near its 2 ms budget and still spaces rays 3.6 cm apart at 4 m",
        choices=(1, 2, 4),
    )
    z_min_m: float = setting(
        0.05,
        "lowest obstacle height above the floor at the robot; the floor is not an obstacle"
        " (see floor_tilt_margin_deg for how the threshold grows with range)",
        "m", min=0.0, max=1.0,
    )
    floor_tilt_margin_deg: float = setting(
        1.25,
        "the height threshold grows with range r as z_min_m + r * tan(this), so a camera pitched"
        " this much off its calibration does not turn the far floor into obstacles",
        "deg", min=0.0, max=10.0,
    )
    z_max_m: float = setting(
        1.8, "highest obstacle height above the floor (the robot's height plus margin)", "m",
        min=0.0, max=5.0,
    )
    range_max_m: float = setting(
        4.0, "obstacle points farther than this from base_link are ignored", "m",
        min=0.2, max=10.0,
    )
    min_range_m: float = setting(
        0.17, "the depth camera's minimum Z; closer is blind (unknown, never free)", "m",
        min=0.0, max=1.0,
    )
    max_depth_m: float = setting(
        10.0,
        "the depth camera's largest usable Z; farther returns (a saturated 65535 among them)"
        " are invalid: neither obstacle nor free space",
        "m", min=0.5, max=65.0,
    )
    scan_bins: int = setting(90, "number of bearing bins of the scan", min=1, max=2048)
    bearing_span_deg: float = setting(
        87.0, "bearing span covered by the bins, centred on base_link x (D435 HFOV 87)", "deg",
        min=1.0, max=360.0,
    )
    blind_missing_fraction: float = setting(
        0.3,
        "a bin is unknown (possible obstacle inside the minimum range) when more than this"
        " fraction of its pixels that must see the floor at calibration return no depth",
        min=0.0, max=1.0,
    )
    floor_expect_range_m: float = setting(
        3.0, "pixels whose calibrated ray meets the floor within this range must see it", "m",
        min=0.3, max=10.0,
    )
    floor_check: bool = setting(
        True, "fit the floor plane each frame (RANSAC) and flag a camera off its calibration"
    )
    floor_check_every: int = setting(
        10, "floor check: run it every n-th frame (it costs ~0.3 ms); results are held between",
        min=1, max=10000,
    )
    floor_alarm_checks: int = setting(
        3, "floor check: the camera is reported off its calibration after this many failed"
        " checks in a row (people around the robot hide the floor from a check or two and a"
        " plane fitted to what remains is tilted; a camera that moved stays moved)",
        min=1, max=1000,
    )
    floor_band_m: float = setting(
        0.3, "floor check: candidate points lie within this height of the calibrated floor", "m",
        min=0.01, max=1.0,
    )
    floor_fit_range_m: float = setting(
        2.5, "floor check: candidate points lie within this range", "m", min=0.3, max=10.0,
    )
    floor_max_normal_deg: float = setting(
        20.0, "floor check: RANSAC accepts only planes whose normal is this close to vertical",
        "deg", min=1.0, max=45.0,
    )
    floor_tilt_tol_deg: float = setting(
        2.0, "floor check: a fitted floor tilted more than this flags the camera", "deg",
        min=0.1, max=30.0,
    )
    floor_height_tol_m: float = setting(
        0.03, "floor check: a fitted floor offset more than this flags the camera", "m",
        min=0.001, max=0.5,
    )
    floor_min_points: int = setting(
        200, "floor check: fewer candidate points than this gives no verdict", min=3, max=100000
    )
    floor_ransac_iters: int = setting(32, "floor check: RANSAC hypotheses", min=1, max=1000)
    floor_inlier_m: float = setting(
        0.02, "floor check: RANSAC inlier distance", "m", min=0.001, max=0.2
    )
    floor_sample: int = setting(
        512, "floor check: candidate points used (fixed stride subsample)", min=16, max=100000
    )


@dataclass(frozen=True)
class ViewCone:
    """Where the camera can see, per bearing bin, for obstacle memory's ray clearing. A bin
    holds the rays whose bearing from the camera (at `cam_x`, `cam_y` in base_link) falls in it.

    At base_link range r in bin b the camera sees heights from
    `cam_z - low_slope[b] * (r - cam_r)` to `cam_z + high_slope[b] * (r - cam_r)` (conservative:
    the worst column of the bin), and nothing closer than `near_range[b]`. Closer than that it
    measures nothing, but a body there blanks the floor pixels behind it and perception marks
    the bin blind: a bin with `floor_checked[b]` that is not unknown saw past such a body.
    """

    bin_angles: np.ndarray  # (bins,) rad, right to left
    bin_width: float  # rad
    cam_x: float  # camera position in base_link, m
    cam_y: float
    cam_z: float  # camera height above the floor, m
    low_slope: np.ndarray  # (bins,) descent of the lowest ray per metre of range
    high_slope: np.ndarray  # (bins,) rise of the highest ray per metre of range
    near_range: np.ndarray  # (bins,) base range of the minimum-range sphere
    floor_checked: np.ndarray  # (bins,) bool, the bin has pixels that must see the floor
    range_max: float

    @property
    def cam_r(self) -> float:
        """Horizontal distance of the camera from base_link's origin, m."""
        return math.hypot(self.cam_x, self.cam_y)

    def bin_of(self, bearing: np.ndarray) -> np.ndarray:
        """Bin index per bearing (rad); -1 outside the span."""
        lo = float(self.bin_angles[0]) - self.bin_width / 2
        return bin_index(bearing, lo, self.bin_width, len(self.bin_angles))


@dataclass
class PerceptionOutput:
    """One frame's result; arrays are views of Perception's buffers (valid until next call)."""

    points: np.ndarray  # (N, 2) float32 obstacle x, y in base_link
    heights: np.ndarray  # (N,) float32 z of each point in base_link (~ height above the floor)
    scan: np.ndarray  # (bins,) float32 min obstacle range per bin, inf = no obstacle point
    unknown: np.ndarray  # (bins,) bool, nothing usable seen: treat as occupied at blind_range
    blind: np.ndarray  # (bins,) bool, unknown because floor pixels returned no depth
    free_range: np.ndarray  # (bins,) float32 seen-free range per bin (0 where unknown)
    bin_angles: np.ndarray  # (bins,) float32 bin centres, rad, right to left
    blind_range: np.ndarray  # (bins,) float32 base range of the camera's minimum range
    valid_fraction: float  # fraction of (decimated) pixels with a valid depth
    floor_ok: bool | None  # None: floor check off or too little floor in view (floor_* are
    # from the latest frame the check ran on: every floor_check_every frames)
    floor_tilt_deg: float  # fitted floor normal vs vertical (nan when not fitted)
    floor_height_m: float  # fitted floor offset from the calibrated floor (nan when not fitted)
    floor_points: int  # candidate points the floor check used


class Perception:
    """Depth -> obstacle points and scan; constructed once per camera, then `process()` per frame."""

    def __init__(self, intrinsics: DepthIntrinsics, mount: CameraMount,
                 config: PerceptionConfig | None = None) -> None:
        cfg = config if config is not None else PerceptionConfig()
        self.config = cfg
        self.intrinsics = intrinsics
        d = cfg.decimation
        self._d = d
        us = np.arange(0, intrinsics.width, d, dtype=np.float64)
        vs = np.arange(0, intrinsics.height, d, dtype=np.float64)
        self.shape = (len(vs), len(us))
        h, w = self.shape
        m = h * w
        # rays in optical frame with z = 1 (so the ray parameter is Z), then into base_link
        ox = (us - intrinsics.cx) / intrinsics.fx
        oy = (vs - intrinsics.cy) / intrinsics.fy
        r_bl = rpy_matrix(*(math.radians(a) for a in mount.rpy_deg)) @ R_LINK_OPTICAL
        self.rotation = r_bl
        self.translation = np.asarray(mount.translation_m, dtype=np.float64)
        rays_o = np.empty((3, h, w))
        rays_o[0] = ox[None, :]
        rays_o[1] = oy[:, None]
        rays_o[2] = 1.0
        rays_b = np.tensordot(r_bl, rays_o, axes=1)  # (3, h, w) base_link direction per unit Z
        rho = np.hypot(rays_b[0], rays_b[1])  # horizontal metres per metre of Z
        tan_m = math.tan(math.radians(cfg.floor_tilt_margin_deg))
        tx, ty, tz = self.translation
        self._rx = rays_b[0].astype(F32).ravel()
        self._ry = rays_b[1].astype(F32).ravel()
        self._rz = rays_b[2].astype(F32).ravel()
        # height test with the range-growing threshold folded into one linear test in Z:
        # tz + Z*rz - tan_m*(Z*rho) >= z_min  <=>  Z*(rz - tan_m*rho) >= z_min - tz
        self._rz_low = (rays_b[2] - tan_m * rho).astype(F32).ravel()
        self._c_low = F32(cfg.z_min_m - tz)
        self._c_high = F32(cfg.z_max_m - tz)
        self._rho = rho.astype(F32)  # (h, w)
        self._unit = F32(intrinsics.depth_unit_m)
        self._zmin_sensor = F32(max(cfg.min_range_m, 1e-3))
        self._zmax_sensor = F32(cfg.max_depth_m)
        self._tx, self._ty, self._tz = F32(tx), F32(ty), F32(tz)

        # bins (right to left)
        n = cfg.scan_bins
        span = math.radians(cfg.bearing_span_deg)
        self._bin_lo = -span / 2
        self._bin_w = span / n
        self.bin_angles = (self._bin_lo + (np.arange(n) + 0.5) * self._bin_w).astype(F32)
        # column -> bin for the per-bin statistics (bearing of the ray through the centre row)
        vc = min(round(intrinsics.cy / d), h - 1)
        col_bearing = np.arctan2(rays_b[1, vc], rays_b[0, vc])
        col_bin = np.floor((col_bearing - self._bin_lo) / self._bin_w).astype(np.intp)
        col_bin[(col_bin < 0) | (col_bin >= n)] = n  # overflow bin, dropped
        self._col_bin = col_bin
        # expected floor pixels: calibrated ray meets the floor within floor_expect_range_m
        with np.errstate(divide="ignore", invalid="ignore"):
            z_floor = np.where(rays_b[2] < 0, -tz / rays_b[2], 1e9)
        fx = tx + z_floor * rays_b[0]
        fy = ty + z_floor * rays_b[1]
        self._expect_floor = ((z_floor >= cfg.min_range_m) & (np.hypot(fx, fy)
                                                             <= cfg.floor_expect_range_m))
        self._expected = np.bincount(col_bin, weights=self._expect_floor.sum(axis=0),
                                     minlength=n + 1)[:n]
        # view cone per bin (for memory clearing): worst column's lowest / highest ray
        low = np.full(n + 1, np.inf)
        high = np.full(n + 1, np.inf)
        col_low = np.max(-rays_b[2] / np.maximum(rho, 1e-9), axis=0)  # descent per metre
        col_high = np.max(rays_b[2] / np.maximum(rho, 1e-9), axis=0)
        np.minimum.at(low, col_bin, col_low)
        np.minimum.at(high, col_bin, col_high)
        low, high = low[:n], high[:n]
        low[~np.isfinite(low)] = 0.0
        high[~np.isfinite(high)] = 0.0
        cam_r = float(math.hypot(tx, ty))
        near = np.full(n, cam_r + cfg.min_range_m * float(rho.max()), dtype=F32)
        self.blind_range = near
        self._cam_proj = (tx * np.cos(self.bin_angles) + ty * np.sin(self.bin_angles)).astype(F32)
        self.view = ViewCone(self.bin_angles.astype(np.float64), self._bin_w, float(tx),
                             float(ty), float(tz), low, high, near.astype(np.float64),
                             self._expected > 0, cfg.range_max_m)

        # preallocated per-frame buffers
        self._z = np.empty(m, dtype=F32)
        self._a = np.empty(m, dtype=F32)
        self._b = np.empty(m, dtype=F32)
        self._mask = np.empty(m, dtype=bool)
        self._mask2 = np.empty(m, dtype=bool)
        self._mask3 = np.empty(m, dtype=bool)
        self._hr = np.empty((h, w), dtype=F32)
        self._colmax = np.empty(w, dtype=F32)
        self._maxpts = m
        self._pts = np.empty((m, 2), dtype=F32)
        self._hts = np.empty(m, dtype=F32)
        self._scan = np.empty(n, dtype=F32)
        self._free = np.empty(n, dtype=F32)
        self._unknown = np.empty(n, dtype=bool)
        self._blind = np.empty(n, dtype=bool)
        self._rng = np.random.default_rng(0)  # RANSAC hypotheses: seeded, reproducible
        self._frames = 0
        self._floor: tuple[bool | None, float, float, int] = (None, math.nan, math.nan, 0)

    # ------------------------------------------------------------------ per frame
    def process(self, depth: np.ndarray, decimated: bool = False) -> PerceptionOutput:
        """uint16 Z16 depth (H, W) in intrinsics.depth_unit_m -> PerceptionOutput.
        `decimated`: `depth` is already every decimation-th pixel (a replayed recording)."""
        cfg = self.config
        d = self._d
        h, w = self.shape
        intr = self.intrinsics
        if decimated:
            if depth.shape != self.shape:
                raise ValueError(f"decimated depth image {depth.shape} does not match the"
                                 f" intrinsics decimated by {d} {self.shape}")
        elif depth.shape != (intr.height, intr.width):
            raise ValueError(f"depth image {depth.shape} does not match the intrinsics "
                             f"({intr.height}, {intr.width})")
        n = cfg.scan_bins
        z2 = self._z.reshape(h, w)
        src = depth if decimated or d == 1 else depth[::d, ::d]
        np.multiply(src, self._unit, out=z2, casting="unsafe")
        z = self._z
        valid, mask, tmp = self._mask2, self._mask, self._mask3
        np.greater_equal(z, self._zmin_sensor, out=valid)
        np.less_equal(z, self._zmax_sensor, out=tmp)
        valid &= tmp
        n_valid = int(np.count_nonzero(valid))
        # height band (the lower threshold grows with range, folded into _rz_low) and validity
        np.multiply(z, self._rz_low, out=self._a)
        np.greater_equal(self._a, self._c_low, out=mask)
        np.multiply(z, self._rz, out=self._b)
        np.less_equal(self._b, self._c_high, out=tmp)
        mask &= tmp
        mask &= valid
        idx = np.flatnonzero(mask)
        zs = z[idx]
        x = zs * self._rx[idx]
        x += self._tx
        y = zs * self._ry[idx]
        y += self._ty
        r = np.hypot(x, y)
        keep = r <= F32(cfg.range_max_m)
        if not keep.all():
            idx, zs, x, y, r = idx[keep], zs[keep], x[keep], y[keep], r[keep]
        k = len(idx)
        pts = self._pts[:k]
        pts[:, 0] = x
        pts[:, 1] = y
        hts = self._hts[:k]
        np.multiply(zs, self._rz[idx], out=hts)
        hts += self._tz
        # scan: min range per bearing bin
        scan = self._scan
        scan.fill(np.inf)
        if k:
            bins = np.floor((np.arctan2(y, x) - F32(self._bin_lo)) * F32(1.0 / self._bin_w))
            bi = bins.astype(np.intp)
            inside = (bi >= 0) & (bi < n)
            np.minimum.at(scan, bi[inside], r[inside])
        # per-bin statistics by column groups: valid count, farthest return, missing floor
        hr = self._hr
        hr.fill(0.0)
        valid2 = valid.reshape(h, w)
        np.multiply(z2, self._rho, out=hr, where=valid2)  # invalid and sub-minimum: not free
        np.max(hr, axis=0, out=self._colmax)
        far = np.zeros(n + 1, dtype=F32)
        np.maximum.at(far, self._col_bin, self._colmax)
        far = far[:n] + self._cam_proj  # |c + d| >= |d| + c.u: never overstates
        vcount = np.bincount(self._col_bin, weights=np.count_nonzero(valid2, axis=0),
                             minlength=n + 1)[:n]
        miss2 = tmp.reshape(h, w)
        np.logical_not(valid2, out=miss2)  # no return, or one the camera cannot give: not floor
        miss2 &= self._expect_floor
        missing = np.bincount(self._col_bin, weights=np.count_nonzero(miss2, axis=0),
                              minlength=n + 1)[:n]
        blind = self._blind
        np.greater(missing, cfg.blind_missing_fraction * self._expected, out=blind)
        blind &= self._expected > 0
        unknown = self._unknown
        np.equal(vcount, 0, out=unknown)
        unknown |= blind
        free = self._free
        np.minimum(far, scan, out=free)
        np.minimum(free, F32(cfg.range_max_m), out=free)
        free[unknown] = 0.0
        m = z.size
        self._frames += 1
        floor = self._floor
        return PerceptionOutput(
            points=pts, heights=hts, scan=scan, unknown=unknown, blind=blind, free_range=free,
            bin_angles=self.bin_angles, blind_range=self.blind_range,
            valid_fraction=n_valid / m if m else 0.0, floor_ok=floor[0],
            floor_tilt_deg=floor[1], floor_height_m=floor[2], floor_points=floor[3],
        )

    # ------------------------------------------------------------------ floor check
    @property
    def floor_check_due(self) -> bool:
        """True when floor_check_every frames have been processed since the last check."""
        return self.config.floor_check and self._frames >= self.config.floor_check_every

    def check_floor(self) -> FloorVerdict:
        """Fit the floor in the frame last given to `process()` (its buffers are still in place:
        call it before the next `process()`). The loop runs it in the slack after the cycle's
        command has gone out, so a health check never delays a command; the verdict is held
        and reported with every later output."""
        self._frames = 0
        self._floor = self._floor_check(self._z, self._mask2)
        return FloorVerdict(*self._floor)

    def _floor_check(self, z: np.ndarray, valid: np.ndarray):
        """RANSAC floor plane near the calibrated floor, normal near vertical; then SVD refit."""
        cfg = self.config
        # candidates: valid, height within floor_band of 0, horizontal range within fit range
        hgt = self._b  # Z * rz, height = tz + hgt
        np.add(hgt, self._tz, out=self._a)
        cand = np.abs(self._a) <= F32(cfg.floor_band_m)
        cand &= valid
        idx = np.flatnonzero(cand)
        if len(idx) == 0:
            return None, math.nan, math.nan, 0
        zs = z[idx]
        rng_h = zs * self._rho.ravel()[idx]
        sel = rng_h <= F32(cfg.floor_fit_range_m)
        idx, zs = idx[sel], zs[sel]
        npts = len(idx)
        if npts < cfg.floor_min_points:
            return None, math.nan, math.nan, npts
        if npts > cfg.floor_sample:
            step = npts / cfg.floor_sample
            pick = (np.arange(cfg.floor_sample) * step).astype(np.intp)
            idx, zs = idx[pick], zs[pick]
        p = np.empty((len(idx), 3))
        p[:, 0] = zs * self._rx[idx] + self._tx
        p[:, 1] = zs * self._ry[idx] + self._ty
        p[:, 2] = zs * self._rz[idx] + self._tz
        k = cfg.floor_ransac_iters
        tri = self._rng.integers(0, len(p), size=(k, 3))
        a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
        nrm = np.cross(b - a, c - a)
        ln = np.linalg.norm(nrm, axis=1)
        ok = ln > 1e-9
        nrm[ok] /= ln[ok, None]
        nrm[nrm[:, 2] < 0] *= -1
        ok &= nrm[:, 2] >= math.cos(math.radians(cfg.floor_max_normal_deg))
        if not ok.any():
            return False, math.nan, math.nan, npts
        nrm, a = nrm[ok], a[ok]
        off = -(nrm * a).sum(axis=1)  # plane n.p + off = 0
        dist = np.abs(p @ nrm.T + off[None, :])  # (points, hyps)
        score = (dist <= cfg.floor_inlier_m).sum(axis=0)
        best = int(np.argmax(score))
        inl = p[dist[:, best] <= cfg.floor_inlier_m]
        if len(inl) < 3:
            return False, math.nan, math.nan, npts
        cen = inl.mean(axis=0)
        _, _, vt = np.linalg.svd(inl - cen, full_matrices=False)
        nv = vt[2]
        if nv[2] < 0:
            nv = -nv
        tilt = math.degrees(math.acos(min(1.0, float(nv[2]))))
        height = float(nv @ cen) / float(nv[2])  # plane height under base_link origin
        ok_floor = tilt <= cfg.floor_tilt_tol_deg and abs(height) <= cfg.floor_height_tol_m
        return ok_floor, tilt, height, npts
