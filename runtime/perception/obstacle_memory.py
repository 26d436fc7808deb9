"""Obstacle memory: remembers obstacle points in the odom frame after they leave the 87 deg view.

Points are kept one per `cell_m` grid cell (a real observed point, the latest one in that cell)
with the cell's observed height range and the time it was last seen, in fixed-capacity numpy
arrays (`max_points` cells), so memory stays bounded whatever the scene. Each update:

1. decay: cells not seen for more than `decay_s` are dropped, except those within
   `hold_out_of_view_m` of the robot that the camera cannot see now (outside its view, closer
   than its minimum range, above or below it, or in an unknown bin): not seeing them is no
   evidence they are gone, as the tracker's coasting has it (a person standing beside the
   robot must not be forgotten while the robot turns in place and then driven into). The
   robot looks before it forgets: a turn toward a held cell clears it if the place is empty.
   Cells inside a moving track's disc (`mark_moving`) since they were last seen are a walking
   person's trail, not an obstacle: they decay, and the track carries the person
   (coasting out of view); held, a passer-by's trail beside or under the view froze the robot
   among people. Cells inside the camera's minimum range are seen through when the bin saw
   its floor (a body there would have blanked it: perception's blind test);
2. ray clearing: a remembered cell that the current frame had in view and saw through (its range
   in its bearing bin is shorter than that bin's free range by `clear_margin_m`) is dropped.
   Only bins that are not `unknown` clear (0 ... minimum range and no-return bins are unknown,
   not free); only inside `range_max_m`; and, when a `ViewCone` is given, only if the cell's
   height range was inside the camera's vertical field of view at that range (a low box that
   went under the view as the robot approached is NOT cleared by the wall seen behind it). With
   no ViewCone, nothing closer than `clear_min_range_m` is cleared. Heights play no part in
   whether a ray clears, only in whether the cell was in view (height filters must not stop
   clearing, field notes);
3. insert the current frame's points (refreshing cells seen again).

When over capacity the least recently seen cells go first. Pure: the caller passes `t`
(host monotonic seconds) and the pose; nothing reads a clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.config.schema import setting
from runtime.geometry import bin_index, bin_layout, from_frame, into_frame
from runtime.perception.depth_points import PerceptionOutput, ViewCone

F32 = np.float32
_KEY_OFF = 1 << 20  # cell index offset: keys stay positive within +-52 km at 5 cm


@dataclass(frozen=True)
class ObstacleMemoryConfig:
    decay_s: float = setting(
        3.0, "a remembered obstacle point is forgotten this long after it was last seen", "s",
        min=0.0, max=600.0,
    )
    cell_m: float = setting(
        0.05, "memory grid cell: one remembered point per cell", "m", min=0.005, max=1.0
    )
    max_points: int = setting(
        8192, "capacity in cells; over it the least recently seen cells are dropped",
        min=16, max=1_000_000,
    )
    range_max_m: float = setting(
        4.0, "ray clearing acts only within this range of base_link (use perception's)", "m",
        min=0.1, max=20.0,
    )
    hold_out_of_view_m: float = setting(
        1.0, "a remembered cell within this distance of base_link that the camera cannot see"
        " now is kept past decay_s (not seeing it is no evidence it is gone); 0 = every cell"
        " decays", "m", min=0.0, max=5.0,
    )
    clear_margin_m: float = setting(
        0.1, "a cell is cleared only if the bin saw free space this much beyond it", "m",
        min=0.0, max=2.0,
    )
    moving_track_margin_m: float = setting(
        0.1, "a remembered cell within a moving track's radius plus this is the walker's trail:"
        " it decays and is not held out of view", "m", min=0.0, max=1.0,
    )
    clear_min_range_m: float = setting(
        1.2,
        "without a view cone: cells closer than this are never cleared (they may be under the"
        " camera's view)", "m", min=0.0, max=20.0,
    )


class ObstacleMemory:
    """Bounded odom-frame point memory with decay and ray clearing."""

    def __init__(self, config: ObstacleMemoryConfig | None = None) -> None:
        # The latest frame's points in odom, one per cell: what the tracker clusters (a depth
        # image stacks hundreds of points per cell; clustering cost grows with points).
        self.frame_points = np.empty((0, 2))
        self.config = config if config is not None else ObstacleMemoryConfig()
        c = self.config.max_points
        self._key = np.empty(c, dtype=np.int64)
        self._x = np.empty(c, dtype=np.float64)
        self._y = np.empty(c, dtype=np.float64)
        self._zlo = np.empty(c, dtype=F32)
        self._zhi = np.empty(c, dtype=F32)
        self._t = np.empty(c, dtype=np.float64)
        # held by the last update: unseen now and close, so alive past decay_s (see update)
        self._held = np.zeros(c, dtype=bool)
        # inside a moving track's disc since last seen: a walker's trail, never held
        self._moving = np.zeros(c, dtype=bool)
        self._n = 0
        self.t_last = -math.inf
        self.cleared_total = 0
        self.decayed_total = 0
        self.dropped_total = 0  # lost to the capacity limit
        # scratch grid for one frame's points (+-range_max around the robot), reset after use
        self._grid_half = math.ceil((self.config.range_max_m + 0.5) / self.config.cell_m)
        gs = 2 * self._grid_half + 1
        self._g_rep = np.zeros(gs * gs, dtype=np.intp)
        self._g_lo = np.full(gs * gs, np.inf, dtype=F32)
        self._g_hi = np.full(gs * gs, -np.inf, dtype=F32)

    def __len__(self) -> int:
        return self._n

    # ------------------------------------------------------------------ update
    def update_from(self, out: PerceptionOutput, pose_odom: tuple[float, float, float],
                    t: float, view: ViewCone | None = None) -> None:
        """Convenience: one perception output (its free_range clears, its heights are kept)."""
        self.update(out.points, pose_odom, out.free_range, out.unknown, out.bin_angles, t,
                    heights=out.heights, view=view)

    def update(self, points_base: np.ndarray, pose_odom: tuple[float, float, float],
               scan: np.ndarray, unknown: np.ndarray, bin_angles: np.ndarray, t: float, *,
               heights: np.ndarray | None = None, view: ViewCone | None = None) -> None:
        """Decay, clear by the current frame, insert its points.

        points_base: (N, 2) obstacle points in base_link; pose_odom: (x, y, theta) of base_link
        in odom at the frame's time; scan: (bins,) range per bin up to which the bin was seen free
        (perception's `free_range`; its `scan` works too but clears up to range_max where no
        obstacle was seen); unknown: (bins,) bool, never clears; bin_angles: (bins,) evenly spaced
        bin centres in rad, right to left; t: seconds; heights: (N,) heights of the points (kept
        per cell for the view test; without them a cell spans 0 ... inf); view: the camera's
        ViewCone (Perception.view).
        """
        cfg = self.config
        self.t_last = t
        px, py, th = pose_odom
        n = self._n
        if n:
            visible, r, k = self._visible(px, py, th, unknown, bin_angles, view)
            self._held[:n] = ~visible & (r <= cfg.hold_out_of_view_m) & ~self._moving[:n]
            alive = ((t - self._t[:n]) <= cfg.decay_s) | self._held[:n]
            self.decayed_total += int(n - np.count_nonzero(alive))
            free = np.minimum(np.asarray(scan, dtype=np.float64)[k], cfg.range_max_m)
            clear = visible & (r < free - cfg.clear_margin_m) & alive
            self.cleared_total += int(np.count_nonzero(clear))
            alive &= ~clear
            self._compact(alive)
        pts = np.asarray(points_base)
        self.frame_points = np.empty((0, 2))
        if len(pts):
            self._insert(pts, heights, px, py, th, t)

    def _visible(self, px, py, th, unknown, bin_angles, view
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which remembered cells the camera sees now (inside the bearing span, in a bin that
        is not unknown, within range_max and, with a ViewCone, beyond its minimum range with
        the cell's heights in its vertical view; without one, beyond clear_min_range_m), their
        range from base_link and their bearing bin (0 for those outside the span)."""
        cfg = self.config
        n = self._n
        bx, by = into_frame(self._x[:n] - px, self._y[:n] - py, th)
        r = np.hypot(bx, by)
        # bearing from the camera, as perception bins its rays: beside the robot the bearing
        # from base_link can fall in a bin whose rays pass the cell by
        ox, oy = (0.0, 0.0) if view is None else (view.cam_x, view.cam_y)  # no view: no offset
        k = bin_index(np.arctan2(by - oy, bx - ox), *bin_layout(bin_angles), len(bin_angles))
        inside = k >= 0
        kk = np.where(inside, k, 0)
        visible = inside & ~np.asarray(unknown)[kk] & (r <= cfg.range_max_m)
        if view is None:
            visible &= r >= cfg.clear_min_range_m
        else:
            zlo, zhi = self._zlo[:n], self._zhi[:n]
            dr = np.maximum(r - view.cam_r, 0.0)
            z_low = view.cam_z - view.low_slope[kk] * dr
            z_high = view.cam_z + view.high_slope[kk] * dr
            in_view = (zhi >= z_low) & (zlo <= z_high)
            # inside the minimum range: a body spanning the view's lower half there (every ray
            # that meets the floor) blanks the bin's floor pixels, which makes the bin blind
            blanks_floor = view.floor_checked[kk] & (zlo <= z_low) & (zhi >= view.cam_z)
            visible &= np.where(r >= view.near_range[kk], in_view, blanks_floor)
        return visible, r, kk

    def _compact(self, keep: np.ndarray) -> None:
        m = int(np.count_nonzero(keep))
        if m == self._n:
            return
        for a in (self._key, self._x, self._y, self._zlo, self._zhi, self._t, self._held,
                  self._moving):
            a[:m] = a[: self._n][keep]
        self._n = m

    def _insert(self, pts, heights, px, py, th, t) -> None:
        cfg = self.config
        ox, oy = from_frame(px, py, th, pts[:, 0].astype(np.float64), pts[:, 1])
        ix = np.floor(ox / cfg.cell_m).astype(np.int64)
        iy = np.floor(oy / cfg.cell_m).astype(np.int64)
        hz = None if heights is None else np.asarray(heights, dtype=F32)
        # cells of this frame, one representative point each: a dense scratch grid around the
        # robot (no sort); points outside it (none from perception) take the np.unique path
        gh = self._grid_half
        gs = 2 * gh + 1
        ix0 = math.floor(px / cfg.cell_m) - gh
        iy0 = math.floor(py / cfg.cell_m) - gh
        gx, gy = ix - ix0, iy - iy0
        ing = (gx >= 0) & (gx < gs) & (gy >= 0) & (gy < gs)
        flat = (gx * gs + gy)[ing]
        src = np.flatnonzero(ing)
        self._g_rep[flat] = src  # last point written per cell is its representative
        # a point is its cell's representative iff the grid kept its index: one per cell, found
        # in O(points) without scanning the whole grid
        is_rep = self._g_rep[flat] == src
        cells, rep = flat[is_rep], src[is_rep]
        ukeys = ((cells // gs + ix0 + _KEY_OFF) << 32) | (cells % gs + iy0 + _KEY_OFF)
        ux, uy = ox[rep], oy[rep]
        if hz is None:
            zlo = np.zeros(len(cells), dtype=F32)
            zhi = np.full(len(cells), np.inf, dtype=F32)
        else:
            hs = hz[src]
            np.minimum.at(self._g_lo, flat, hs)
            np.maximum.at(self._g_hi, flat, hs)
            zlo, zhi = self._g_lo[cells], self._g_hi[cells]
            self._g_lo[cells] = np.inf
            self._g_hi[cells] = -np.inf
        if not ing.all():
            out = np.flatnonzero(~ing)
            keys = ((ix[out] + _KEY_OFF) << 32) | (iy[out] + _KEY_OFF)
            k2, first, inv = np.unique(keys, return_index=True, return_inverse=True)
            lo2 = np.zeros(len(k2), dtype=F32)
            hi2 = np.full(len(k2), np.inf, dtype=F32)
            if hz is not None:
                lo2.fill(np.inf)
                hi2.fill(-np.inf)
                np.minimum.at(lo2, inv, hz[out])
                np.maximum.at(hi2, inv, hz[out])
            ukeys = np.concatenate([ukeys, k2])
            ux = np.concatenate([ux, ox[out[first]]])
            uy = np.concatenate([uy, oy[out[first]]])
            zlo, zhi = np.concatenate([zlo, lo2]), np.concatenate([zhi, hi2])
        self.frame_points = np.column_stack([ux, uy])
        n = self._n
        # match against remembered cells
        order = np.argsort(self._key[:n])
        sk = self._key[:n][order]
        pos = np.searchsorted(sk, ukeys)
        pos_c = np.minimum(pos, max(n - 1, 0))
        hit = (pos < n) & (sk[pos_c] == ukeys) if n else np.zeros(len(ukeys), dtype=bool)
        if hit.any():
            slot = order[pos_c[hit]]
            self._x[slot], self._y[slot] = ux[hit], uy[hit]
            self._zlo[slot] = np.minimum(self._zlo[slot], zlo[hit])
            self._zhi[slot] = np.maximum(self._zhi[slot], zhi[hit])
            self._t[slot] = t
            self._held[slot] = False
            self._moving[slot] = False
        new = ~hit
        m = int(np.count_nonzero(new))
        cap = cfg.max_points
        if n + m > cap:
            # make room: drop the least recently seen remembered cells, then if still too many
            # new cells (one frame over capacity), keep the first `cap` of them
            m = min(m, cap)
            room = cap - m
            if room < n:
                keep_idx = np.argsort(self._t[:n], kind="stable")[n - room:]
                keep = np.zeros(n, dtype=bool)
                keep[keep_idx] = True
                self.dropped_total += n - room
                self._compact(keep)
                n = self._n
            sel = np.flatnonzero(new)
            self.dropped_total += len(sel) - m
            new = np.zeros(len(ukeys), dtype=bool)
            new[sel[:m]] = True
        e = n + m
        self._key[n:e] = ukeys[new]
        self._x[n:e] = ux[new]
        self._y[n:e] = uy[new]
        self._zlo[n:e] = zlo[new]
        self._zhi[n:e] = zhi[new]
        self._t[n:e] = t
        self._held[n:e] = False
        self._moving[n:e] = False
        self._n = e

    def mark_moving(self, centres: np.ndarray, radii: np.ndarray) -> None:
        """Mark the cells within these discs (odom centres (K, 2), radii (K,): the moving tracks
        this frame hit) as a walker's: nothing static stands where a person walks now, so they
        decay and are not held. A cell seen again later is judged again."""
        n = self._n
        x, y, moving = self._x[:n], self._y[:n], self._moving[:n]
        # one disc at a time: an (n, K) distance matrix cost 3 ms at capacity with 20 walkers
        for (cx, cy), r in zip(centres, radii):
            reach = float(r) + self.config.moving_track_margin_m
            moving |= (x - cx) ** 2 + (y - cy) ** 2 <= reach * reach

    # ------------------------------------------------------------------ queries
    def points_odom(self, t: float | None = None) -> np.ndarray:
        """(M, 2) float64 remembered points in odom alive at t (default: the last update's t):
        seen within decay_s, or held by the last update (unseen beside the robot)."""
        n = self._n
        tt = self.t_last if t is None else t
        alive = ((tt - self._t[:n]) <= self.config.decay_s) | self._held[:n]
        return np.stack([self._x[:n][alive], self._y[:n][alive]], axis=1)

    def points_base(self, pose_odom: tuple[float, float, float],
                    t: float | None = None) -> np.ndarray:
        """(M, 2) float32 remembered points still alive at t, in base_link at `pose_odom`."""
        p = self.points_odom(t)
        px, py, th = pose_odom
        out = np.empty((len(p), 2), dtype=F32)
        out[:, 0], out[:, 1] = into_frame(p[:, 0] - px, p[:, 1] - py, th)
        return out
