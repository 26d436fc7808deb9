"""Synthetic D435 depth: a vectorised ray caster over a floor, vertical cylinders and boxes.

Frames (REP 103/105): world z up with the floor at z = 0; base_link at (x, y, base_z) with yaw
theta; camera_link in base_link from a `CameraMount` (translation + roll/pitch/yaw, pitch > 0
tilts the camera down); the optical frame is fixed to camera_link (optical z = link x, optical
x = -link y, optical y = -link z).

Output is uint16 Z16 in `intrinsics.depth_unit_m`: Z along the optical axis (not ray length),
0 where nothing is hit within `max_range_m` or closer than `min_range_m`. Optional noise:
sigma_z = k * z^2 (seeded) and random dropout next to large depth discontinuities.

Render what is read: with `decimation` d the renderer casts only the rays of every d-th pixel
in both directions, the grid the world model reads at `perception.decimation` d, and returns
them as a (ceil(H/d), ceil(W/d)) image whose intrinsics are the full ones divided by d. Its
pixel (i, j) is the full image's pixel (d·i, d·j), bit for bit without noise (the same rays,
elementwise arithmetic only), and the world model deprojects it along the same rays (d is 1, 2
or 4: dividing the intrinsics by a power of two is exact). With noise, each kept pixel gets the
same depth noise; edge dropout looks at the neighbouring rendered pixels, d pixels apart, with
the same jump threshold and probability.

Speed: ray directions are precomputed once (optical frame, z component 1, so the ray parameter
is Z itself); per frame one 3x3 rotation of all rays, then per object only the pixel rectangle
its bounding box projects to is intersected (closed form, numpy, float32). No loop over pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from drivers.depth_source import D435_848x480, DepthIntrinsics
from runtime.config.settings import CameraMount
from runtime.geometry import R_LINK_OPTICAL, rpy_matrix

F32 = np.float32

@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder standing on the floor (static post or a person)."""

    x: float
    y: float
    radius: float
    height: float = 1.7


@dataclass(frozen=True)
class Box:
    """Box standing on the floor: centre (x, y), sides lx, ly, yaw about z (rad), height."""

    x: float
    y: float
    lx: float
    ly: float
    yaw: float = 0.0
    height: float = 1.0


def wall(x0: float, y0: float, x1: float, y1: float, thickness: float = 0.1,
         height: float = 2.5) -> Box:
    """A wall from (x0, y0) to (x1, y1) as a thin box."""
    dx, dy = x1 - x0, y1 - y0
    return Box((x0 + x1) / 2, (y0 + y1) / 2, math.hypot(dx, dy), thickness,
               math.atan2(dy, dx), height)


@dataclass
class Scene:
    cylinders: Sequence[Cylinder] = field(default_factory=list)
    boxes: Sequence[Box] = field(default_factory=list)
    floor: bool = True


_CORNER_SIGNS = np.array([(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (0, 1)],
                         dtype=float)


def _corners(objects: list[tuple[float, float, float, float, float, float]]) -> np.ndarray:
    """(K, 8, 3) corners of upright boxes (x, y, half x, half y, yaw, height) on the floor."""
    a = np.array(objects, dtype=float)
    c, s = np.cos(a[:, 4:5]), np.sin(a[:, 4:5])
    lx = _CORNER_SIGNS[None, :, 0] * a[:, 2:3]
    ly = _CORNER_SIGNS[None, :, 1] * a[:, 3:4]
    return np.stack([a[:, 0:1] + c * lx - s * ly, a[:, 1:2] + s * lx + c * ly,
                     _CORNER_SIGNS[None, :, 2] * a[:, 5:6]], axis=2)


DECIMATIONS = (1, 2, 4)  # the perception decimations (powers of two: exact intrinsics)


def decimated(k: DepthIntrinsics, d: int) -> DepthIntrinsics:
    """Intrinsics of every d-th pixel of a k image: pixel (i, j) is k's pixel (d·i, d·j)."""
    if d == 1:
        return k
    return DepthIntrinsics(-(-k.width // d), -(-k.height // d), k.fx / d, k.fy / d, k.cx / d,
                           k.cy / d, k.depth_unit_m)


def camera_pose(robot_pose: tuple[float, float, float], mount: CameraMount,
                base_z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_optical 3x3, camera origin in world) for robot pose (x, y, theta)."""
    x, y, th = robot_pose
    r_wb = rpy_matrix(0.0, 0.0, th)
    r_bl = rpy_matrix(*(math.radians(a) for a in mount.rpy_deg))
    origin = np.array([x, y, base_z]) + r_wb @ np.asarray(mount.translation_m, dtype=float)
    return r_wb @ r_bl @ R_LINK_OPTICAL, origin


class DepthRenderer:
    """Renders synthetic depth frames for one camera (intrinsics + mount)."""

    def __init__(
        self,
        intrinsics: DepthIntrinsics = D435_848x480,
        mount: CameraMount | None = None,
        *,
        base_z: float = 0.0,
        min_range_m: float = 0.17,
        max_range_m: float = 10.0,
        noise_k: float = 0.001,
        edge_dropout_p: float = 0.5,
        edge_jump_m: float = 0.25,
        seed: int = 0,
        decimation: int = 1,
    ) -> None:
        if decimation not in DECIMATIONS:
            raise ValueError(f"decimation must be one of {DECIMATIONS}, got {decimation}")
        self.full_intrinsics = intrinsics
        self.decimation = d = decimation
        self.intrinsics = decimated(intrinsics, d)
        self.mount = mount if mount is not None else CameraMount()
        self.base_z = base_z
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self.noise_k = noise_k
        self.edge_dropout_p = edge_dropout_p
        self.edge_jump_m = edge_jump_m
        self.rng = np.random.default_rng(seed)
        h, w = self.intrinsics.height, self.intrinsics.width
        u = (np.arange(0, intrinsics.width, d, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
        v = (np.arange(0, intrinsics.height, d, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
        rays = np.empty((3, h, w), dtype=F32)  # optical frame, z = 1: ray parameter == Z
        rays[0] = u[None, :]
        rays[1] = v[:, None]
        rays[2] = 1.0
        self._rays = rays.reshape(3, h * w)
        self._d = np.empty((3, h * w), dtype=F32)  # world-frame directions, per frame
        self._z = np.empty((h, w), dtype=F32)
        self._out = np.empty((h, w), dtype=np.uint16)

    # ------------------------------------------------------------------ geometry
    def render_z(self, robot_pose: tuple[float, float, float], scene: Scene) -> np.ndarray:
        """Noise-free Z in metres (float32, HxW), inf where nothing is hit. Reused buffer."""
        r, o = camera_pose(robot_pose, self.mount, self.base_z)
        h, w = self.intrinsics.height, self.intrinsics.width
        r32 = r.astype(F32)
        for i in range(3):  # elementwise, not a BLAS product: a pixel's ray must not depend on
            # how many others are cast with it (decimated == full, bit for bit)
            np.multiply(r32[i, 0], self._rays[0], out=self._d[i])
            self._d[i] += r32[i, 1] * self._rays[1]
            self._d[i] += r32[i, 2] * self._rays[2]
        d = self._d.reshape(3, h, w)
        z = self._z
        z.fill(np.inf)
        oz = F32(o[2])
        if scene.floor and o[2] > 0:
            np.divide(-oz, d[2], out=z, where=d[2] < 0)
        objects = [(c.x, c.y, c.radius, c.radius, 0.0, c.height) for c in scene.cylinders]
        objects += [(b.x, b.y, b.lx / 2, b.ly / 2, b.yaw, b.height) for b in scene.boxes]
        rects = self._rects(_corners(objects), r, o) if objects else []
        for cyl, rect in zip(scene.cylinders, rects):
            if rect is not None:
                self._cylinder(cyl, rect, o, d, z)
        for box, rect in zip(scene.boxes, rects[len(scene.cylinders):]):
            if rect is not None:
                self._box(box, rect, o, d, z)
        return z

    def _rects(self, corners: np.ndarray, r: np.ndarray, o: np.ndarray
               ) -> list[tuple[int, int, int, int] | None]:
        """Per object, the rendered-pixel rectangle (v0, v1, u0, u1) covering its world corners
        (K, 8, 3), or None if not visible: the full image's pixel rectangle, then the rendered
        pixels inside it. One projection for all objects."""
        p = (corners - o) @ r  # optical coordinates
        zs = p[..., 2]
        behind = zs <= 1e-3
        k, d = self.full_intrinsics, self.decimation
        with np.errstate(divide="ignore", invalid="ignore"):
            us = k.fx * p[..., 0] / zs + k.cx
            vs = k.fy * p[..., 1] / zs + k.cy
        hidden = (behind.all(axis=1) | (zs.min(axis=1) > self.max_range_m)).tolist()
        across = behind.any(axis=1).tolist()  # partly behind the camera: the whole image
        lo_u, hi_u = us.min(axis=1).tolist(), us.max(axis=1).tolist()
        lo_v, hi_v = vs.min(axis=1).tolist(), vs.max(axis=1).tolist()
        h, w = self.intrinsics.height, self.intrinsics.width
        out: list[tuple[int, int, int, int] | None] = []
        for i, gone in enumerate(hidden):
            if gone:
                out.append(None)
                continue
            if across[i]:
                out.append((0, h, 0, w))
                continue
            u0, u1 = max(math.floor(lo_u[i]) - 1, 0), min(math.ceil(hi_u[i]) + 2, k.width)
            v0, v1 = max(math.floor(lo_v[i]) - 1, 0), min(math.ceil(hi_v[i]) + 2, k.height)
            u0, u1, v0, v1 = -(-u0 // d), -(-u1 // d), -(-v0 // d), -(-v1 // d)  # d·j in [lo, hi)
            out.append(None if u0 >= u1 or v0 >= v1 else (v0, v1, u0, u1))
        return out

    def _cylinder(self, cyl: Cylinder, rect: tuple[int, int, int, int], o, d, z) -> None:
        v0, v1, u0, u1 = rect
        dx, dy, dz = d[0, v0:v1, u0:u1], d[1, v0:v1, u0:u1], d[2, v0:v1, u0:u1]
        zz = z[v0:v1, u0:u1]
        ex, ey, oz = F32(o[0] - cyl.x), F32(o[1] - cyl.y), F32(o[2])
        c = F32(ex * ex + ey * ey - cyl.radius**2)
        with np.errstate(invalid="ignore", divide="ignore"):
            if c > 0:  # camera outside: side wall
                a = dx * dx + dy * dy
                b = dx * ex + dy * ey  # half of the usual b
                disc = b * b - a * c
                t = (-b - np.sqrt(disc)) / a  # nan where disc < 0
                hz = oz + t * dz
                ok = (t > 0) & (hz >= 0) & (hz <= F32(cyl.height))
                np.minimum(zz, np.where(ok, t, F32(np.inf)), out=zz)
            if o[2] > cyl.height:  # top cap
                t = (F32(cyl.height) - oz) / dz
                px, py = ex + t * dx, ey + t * dy
                ok = (t > 0) & (px * px + py * py <= F32(cyl.radius**2))
                np.minimum(zz, np.where(ok, t, F32(np.inf)), out=zz)

    def _box(self, box: Box, rect: tuple[int, int, int, int], o, d, z) -> None:
        hx, hy = box.lx / 2, box.ly / 2
        v0, v1, u0, u1 = rect
        dx, dy, dz = d[0, v0:v1, u0:u1], d[1, v0:v1, u0:u1], d[2, v0:v1, u0:u1]
        zz = z[v0:v1, u0:u1]
        c, s = F32(math.cos(box.yaw)), F32(math.sin(box.yaw))
        rx, ry = o[0] - box.x, o[1] - box.y
        lo_x, lo_y = F32(c * rx + s * ry), F32(-s * rx + c * ry)
        ld_x = c * dx + s * dy
        ld_y = -s * dx + c * dy
        with np.errstate(invalid="ignore", divide="ignore"):
            tmin = np.full(zz.shape, -np.inf, dtype=F32)
            tmax = np.full(zz.shape, np.inf, dtype=F32)
            for oc, dc, lo, hi in ((lo_x, ld_x, -hx, hx), (lo_y, ld_y, -hy, hy),
                                   (F32(o[2]), dz, 0.0, box.height)):
                inv = F32(1.0) / dc
                t1 = (F32(lo) - oc) * inv
                t2 = (F32(hi) - oc) * inv
                np.maximum(tmin, np.minimum(t1, t2), out=tmin)
                np.minimum(tmax, np.maximum(t1, t2), out=tmax)
            ok = (tmin <= tmax) & (tmin > 0)
            np.minimum(zz, np.where(ok, tmin, F32(np.inf)), out=zz)

    # ------------------------------------------------------------------ sensor model
    def render(self, robot_pose: tuple[float, float, float], scene: Scene,
               noise: bool = False) -> np.ndarray:
        """uint16 Z16 depth (HxW, a new array), with the D435 noise model if `noise`."""
        z = self.render_z(robot_pose, scene)
        valid = (z >= F32(self.min_range_m)) & (z <= F32(self.max_range_m))
        zm = np.where(valid, z, F32(0.0))
        if noise:  # random numbers only where they act: valid pixels, edge pixels
            clean = zm
            if self.noise_k > 0:
                zm = zm.copy()
                kept = zm[valid]
                n = self.rng.standard_normal(kept.shape, dtype=F32)
                zm[valid] = kept + F32(self.noise_k) * kept * kept * n
            if self.edge_dropout_p > 0:
                jx = np.abs(np.diff(clean, axis=1)) > F32(self.edge_jump_m)
                jy = np.abs(np.diff(clean, axis=0)) > F32(self.edge_jump_m)
                edge = np.zeros(zm.shape, dtype=bool)
                edge[:, 1:] |= jx
                edge[:, :-1] |= jx
                edge[1:, :] |= jy
                edge[:-1, :] |= jy
                at = np.flatnonzero(edge)
                drop = at[self.rng.random(len(at), dtype=F32) < F32(self.edge_dropout_p)]
                valid.ravel()[drop] = False
        units = np.rint(zm / F32(self.intrinsics.depth_unit_m))
        np.clip(units, 1, 65535, out=units)
        out = np.zeros(zm.shape, dtype=np.uint16)
        np.copyto(out, units, where=valid, casting="unsafe")
        return out


def benchmark(n_frames: int = 20, seed: int = 1) -> float:
    """Frames/s at 848x480 with 20 cylinders and 10 boxes (incl. 4 walls), noise on."""
    rng = np.random.default_rng(seed)
    cyl = [Cylinder(float(rng.uniform(0.5, 8)), float(rng.uniform(-4, 4)),
                    float(rng.uniform(0.1, 0.35)), float(rng.uniform(0.5, 1.9))) for _ in range(20)]
    boxes = [Box(float(rng.uniform(1, 8)), float(rng.uniform(-4, 4)), 0.6, 0.4,
                 float(rng.uniform(0, 3)), 0.8) for _ in range(6)]
    boxes += [wall(-1, 5, 9, 5), wall(-1, -5, 9, -5), wall(9, -5, 9, 5), wall(-1, -5, -1, 5)]
    scene = Scene(cyl, boxes)
    rend = DepthRenderer()
    import time

    rend.render((0.0, 0.0, 0.0), scene, noise=True)
    t0 = time.perf_counter()
    for i in range(n_frames):
        rend.render((0.05 * i, 0.0, 0.02 * i), scene, noise=True)
    return n_frames / (time.perf_counter() - t0)


if __name__ == "__main__":
    print(f"{benchmark():.1f} frames/s at 848x480, 20 cylinders + 10 boxes, noise on")
