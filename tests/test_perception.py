"""Perception on synthetic D435 depth (sim_stub.depth_render) and on a real pyrealsense2 recording.

Geometry note: decimation d of an 848x480 image uses exactly the pixels (u, v) = (d*i, d*j), whose
rays equal those of a (848/d)x(480/d) camera with fx/d, fy/d, cx/d, cy/d. The 1,000-frame floor
tests render at that smaller size (same rays, same noise model per pixel) to stay fast, and
perceive with decimation 1 on it: the same pixels a decimation-2 pipeline looks at (the default, 4, looks at a subset of them).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.depth_source import D435_848x480
from drivers.realsense.playback import PlaybackDepthSource
from runtime.config.settings import CameraMount
from runtime.perception.depth_points import FloorVerdict, Perception, PerceptionConfig
from runtime.types import DepthFrame, DepthIntrinsics
from sim_stub.depth_render import Box, Cylinder, DepthRenderer, Scene
from sim_stub.lockstep import widened_d435
from sim_stub.recording import record
from sim_stub.sim_server import BASE_LINK_HEIGHT_M

MOUNT = CameraMount()
CAM_X, CAM_Y = MOUNT.translation_m[0], MOUNT.translation_m[1]


def scaled(k: DepthIntrinsics, d: int) -> DepthIntrinsics:
    return DepthIntrinsics(k.width // d, k.height // d, k.fx / d, k.fy / d, k.cx / d, k.cy / d,
                           k.depth_unit_m)


def renderer(mount: CameraMount = MOUNT, intrinsics=D435_848x480, seed=0) -> DepthRenderer:
    return DepthRenderer(intrinsics, mount, base_z=BASE_LINK_HEIGHT_M, seed=seed)


def boundary_distance(p: np.ndarray, obj) -> np.ndarray:
    """2-D distance of points (N, 2) to the obstacle's outline."""
    if isinstance(obj, Cylinder):
        return np.abs(np.hypot(p[:, 0] - obj.x, p[:, 1] - obj.y) - obj.radius)
    c, s = math.cos(obj.yaw), math.sin(obj.yaw)
    dx, dy = p[:, 0] - obj.x, p[:, 1] - obj.y
    lx, ly = np.abs(c * dx + s * dy) - obj.lx / 2, np.abs(-s * dx + c * dy) - obj.ly / 2
    outside = np.hypot(np.maximum(lx, 0), np.maximum(ly, 0))
    inside = np.minimum(np.maximum(lx, ly), 0)
    return np.abs(outside + inside)


def nearest_visible(obj) -> tuple[float, float]:
    """(range from base_link, bearing) of the nearest outline point the camera can see (dense
    sampling; a point is visible when its outward normal faces the camera)."""
    if isinstance(obj, Cylinder):
        a = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
        nrm = np.stack([np.cos(a), np.sin(a)], 1)
        pts = np.array([obj.x, obj.y]) + obj.radius * nrm
    else:
        t = np.linspace(-0.5, 0.5, 900)
        hx, hy = obj.lx / 2, obj.ly / 2
        loc, nl = [], []
        for sgn in (-1, 1):
            loc.append(np.stack([2 * hx * t, np.full_like(t, sgn * hy)], 1))
            nl.append(np.tile([0.0, sgn], (len(t), 1)))
            loc.append(np.stack([np.full_like(t, sgn * hx), 2 * hy * t], 1))
            nl.append(np.tile([sgn, 0.0], (len(t), 1)))
        loc, nl = np.concatenate(loc), np.concatenate(nl)
        c, s = math.cos(obj.yaw), math.sin(obj.yaw)
        rot = np.array([[c, -s], [s, c]])
        pts = np.array([obj.x, obj.y]) + loc @ rot.T
        nrm = nl @ rot.T
    seen = ((np.array([CAM_X, CAM_Y]) - pts) * nrm).sum(axis=1) > 0
    pts = pts[seen]
    r = np.hypot(pts[:, 0], pts[:, 1])
    i = int(np.argmin(r))
    return float(r[i]), float(math.atan2(pts[i, 1], pts[i, 0]))


def random_scene(rng: np.random.Generator, n: int = 6) -> Scene:
    """n obstacles at distinct bearings (no occlusion), nearest surface 0.2 ... 3.85 m in front of
    the camera (depth Z), within 36 deg of the axis (inside the 87 deg view and range_max 4 m)."""
    bearings = np.linspace(-0.6, 0.6, n) + rng.uniform(-0.03, 0.03, n)
    dists = rng.uniform(0.2, 3.9, n)
    dists[0], dists[-1] = 0.2, 3.85  # always include both ends of the range
    rng.shuffle(dists)
    cyl, boxes = [], []
    spans = []
    for k, (b, dist) in enumerate(zip(bearings, dists)):
        size = float(rng.uniform(0.05, 0.12)) * max(1.0, dist / 2)  # keep >= ~2 bins wide
        # dist is the depth Z of the nearest surface (the D435's ranges are along Z), capped so
        # the obstacle stays inside range_max (4 m from base_link)
        centre = min((dist + size) / math.cos(b), 3.9 - size - CAM_X)
        x, y = CAM_X + centre * math.cos(b), CAM_Y + centre * math.sin(b)
        half = math.asin(min(1.0, 1.45 * size / centre))  # bounding circle seen from the camera
        if any(b - half < hi and lo < b + half for lo, hi in spans):
            continue  # would overlap a neighbour in the image: leave it out (no occlusion)
        spans.append((b - half, b + half))
        if k % 2:
            cyl.append(Cylinder(x, y, size, 1.7))
        else:
            boxes.append(Box(x, y, 2 * size, 2 * size, float(rng.uniform(0, 1.5)), 1.0))
    return Scene(cyl, boxes)


@pytest.mark.parametrize("decimation", [1, 2, 4])
def test_every_obstacle_in_view_is_detected_with_small_point_error(decimation):
    rng = np.random.default_rng(7)
    rend = renderer()
    per = Perception(D435_848x480, MOUNT, PerceptionConfig(decimation=decimation))
    for _ in range(4):
        scene = random_scene(rng)
        objects = list(scene.cylinders) + list(scene.boxes)
        for noise in (False, True):
            out = per.process(rend.render((0.0, 0.0, 0.0), scene, noise=noise))
            pts = out.points
            err = np.min(np.stack([boundary_distance(pts, o) for o in objects]), axis=0)
            if noise:  # sigma_z = 1 mm * z^2 (16 mm at 4 m): the bulk stays within 3 cm
                assert np.percentile(err, 99) <= 0.03
            else:  # geometry alone: every point on an obstacle outline within 3 cm (in fact mm)
                assert err.max() <= 0.03, err.max()
            for o in objects:
                near = boundary_distance(pts, o) <= 0.03
                assert near.sum() >= 5, o
                r0, b0 = nearest_visible(o)
                b = int((b0 - out.bin_angles[0]) / (out.bin_angles[1] - out.bin_angles[0]) + 0.5)
                scan_near = out.scan[max(b - 1, 0): b + 2].min()
                # with noise the per-bin minimum over many points reads early (safe side) by up to
                # a few sigma: sigma_z = 1 mm * z^2
                low_tol = max(0.03, 5 * rend.noise_k * r0 * r0) if noise else 0.03
                assert r0 - low_tol <= scan_near <= r0 + 0.03, (o, r0, scan_near)
                assert not out.unknown[b]


def floor_false_positives(render_mount: CameraMount, frames: int, seed: int) -> int:
    """Render floor-only frames (noise on) from many poses with `render_mount`; perceive with the
    nominal calibration. Half resolution == decimation 2, a superset of the default 4's rays (see module docstring)."""
    k2 = scaled(D435_848x480, 2)
    rend = renderer(render_mount, k2, seed=seed)
    per = Perception(k2, MOUNT, PerceptionConfig(decimation=1, floor_check=False))
    rng = np.random.default_rng(seed)
    count = 0
    for _ in range(frames):
        pose = (float(rng.uniform(-5, 5)), float(rng.uniform(-5, 5)), float(rng.uniform(-3, 3)))
        out = per.process(rend.render(pose, Scene(), noise=True))
        count += len(out.points)
        assert not out.unknown.any()
    return count


def test_no_floor_point_is_an_obstacle_at_calibration():
    assert floor_false_positives(MOUNT, 1000, seed=1) == 0


def test_no_floor_point_is_an_obstacle_with_camera_1deg_1cm_off_calibration():
    # worst sign: the real camera pitched 1 deg further down and 1 cm lower than calibrated makes
    # the floor look higher (1 cm + r * tan 1 deg = 8 cm at 4 m); the threshold
    # z_min 5 cm + r * tan 1.25 deg leaves >= 3 cm at every range.
    x, y, z = MOUNT.translation_m
    worst = CameraMount((x, y, z - 0.01), (0.0, 1.0, 0.0))
    assert floor_false_positives(worst, 1000, seed=2) == 0
    other = CameraMount((x, y, z + 0.01), (0.0, -1.0, 0.0))
    assert floor_false_positives(other, 100, seed=3) == 0


def test_blind_zone_is_unknown_not_free():
    rend = renderer()
    per = Perception(D435_848x480, MOUNT)
    empty = per.process(rend.render((0.0, 0.0, 0.0), Scene(), noise=True))
    assert not empty.unknown.any() and np.isinf(empty.scan).all()
    assert (empty.free_range > 3.0).all()
    # a post 10 cm in front of the lens, inside the 0.17 m minimum range: renders as 0
    post = Cylinder(CAM_X + 0.10 + 0.04, CAM_Y - 0.05, 0.04, 1.7)
    depth = rend.render((0.0, 0.0, 0.0), Scene([post]), noise=True)
    out = per.process(depth)
    bearing = math.atan2(post.y, post.x)
    b = int((bearing - out.bin_angles[0]) / (out.bin_angles[1] - out.bin_angles[0]))
    assert out.unknown[b] and out.blind[b]
    assert out.free_range[b] == 0.0  # nothing in that bearing counts as seen free
    assert np.isinf(out.scan[b])  # no point was measured: unknown carries the information
    assert out.unknown.sum() < len(out.unknown) // 2  # the rest of the view stays known


def test_playback_of_a_recording_gives_the_same_output(tmp_path):
    rend = renderer(seed=5)
    scene = random_scene(np.random.default_rng(3))
    frames = [DepthFrame(rend.render((0.1 * k, 0.0, 0.05 * k), scene, noise=True), k / 30.0, k,
                         D435_848x480) for k in range(4)]
    path = tmp_path / "perception.db3"
    assert record(path, iter(frames), 30.0) == 4
    source = PlaybackDepthSource(path)
    source.start()
    played = []
    try:
        while not source.at_end:
            f = source.poll()
            if f is not None:
                played.append(f)
    finally:
        source.stop()
    assert len(played) == 4
    per_a = Perception(D435_848x480, MOUNT)
    per_b = Perception(played[0].intrinsics, MOUNT)  # intrinsics as stored in the recording
    for want, got in zip(frames, played):
        assert np.array_equal(want.depth, got.depth)
        a = per_a.process(want.depth)
        a_pts, a_scan, a_unk = a.points.copy(), a.scan.copy(), a.unknown.copy()
        b = per_b.process(got.depth)
        assert a_pts.shape == b.points.shape
        np.testing.assert_allclose(b.points, a_pts, atol=1e-4)
        np.testing.assert_allclose(b.scan, a_scan, atol=1e-4)
        assert np.array_equal(b.unknown, a_unk)


def test_floor_check_flags_a_camera_tilted_5_degrees():
    per = Perception(D435_848x480, MOUNT)

    def verdict(rend: DepthRenderer) -> FloorVerdict:
        per.process(rend.render((0.0, 0.0, 0.0), Scene(), noise=True))
        return per.check_floor()

    ok = verdict(renderer())
    assert ok.ok is True and ok.tilt_deg < 0.5
    for rpy in ((0.0, 5.0, 0.0), (0.0, -5.0, 0.0), (5.0, 0.0, 0.0)):
        out = verdict(renderer(CameraMount(MOUNT.translation_m, rpy)))
        assert out.ok is False, rpy
        assert 4.0 < out.tilt_deg < 6.0
    # a camera that dropped 5 cm is flagged too
    x, y, z = MOUNT.translation_m
    out = verdict(renderer(CameraMount((x, y, z - 0.05), (0.0, 0.0, 0.0))))
    assert out.ok is False and out.height_m == pytest.approx(0.05 - 0.01, abs=0.01)


def test_output_is_finite_and_bins_run_right_to_left():
    per = Perception(D435_848x480, MOUNT)
    assert np.all(np.diff(per.bin_angles) > 0)  # right (negative) to left (positive)
    assert per.bin_angles[0] == pytest.approx(-math.radians(87.0) / 2 + per.view.bin_width / 2)
    left = Cylinder(2.0, 1.0, 0.2)
    out = per.process(renderer().render((0.0, 0.0, 0.0), Scene([left])))
    hit = np.flatnonzero(np.isfinite(out.scan))
    assert per.bin_angles[hit].min() > 0  # an obstacle on the left lands in positive bins
    assert np.isfinite(out.points).all()


def test_floor_check_is_due_every_nth_frame_and_its_verdict_is_held():
    per = Perception(D435_848x480, MOUNT, PerceptionConfig(floor_check_every=3))
    x, y, z = MOUNT.translation_m
    tilted = renderer(CameraMount((x, y, z), (0.0, 5.0, 0.0))).render((0.0, 0.0, 0.0), Scene())
    level = renderer().render((0.0, 0.0, 0.0), Scene())
    due, held = [], []
    for d in (level, level, level, tilted, tilted, tilted, level):
        held.append(per.process(d).floor_ok)
        due.append(per.floor_check_due)
        if per.floor_check_due:
            per.check_floor()  # as the loop does, in the slack after the command
    assert due == [False, False, True, False, False, True, False]
    assert held == [None, None, None, True, True, True, False]
    off = Perception(D435_848x480, MOUNT, PerceptionConfig(floor_check=False))
    out = off.process(level)
    assert not off.floor_check_due
    assert out.floor_ok is None and math.isnan(out.floor_tilt_deg)


def test_a_wider_camera_sees_a_person_beside_the_robot_that_the_d435_cannot():
    """eval --camera-hfov's camera: the D435's pixels on a wider sensor. A person at 55 deg is
    outside the D435's 87 deg and inside 120 deg; the floor stays floor."""
    person = Scene([Cylinder(1.2, 1.7, 0.25)])
    narrow = Perception(D435_848x480, MOUNT)
    assert len(narrow.process(renderer().render((0.0, 0.0, 0.0), person)).points) == 0
    k = widened_d435(120.0)
    assert (k.fx, k.fy, k.height) == (D435_848x480.fx, D435_848x480.fy, 480)
    assert math.degrees(2 * math.atan(k.cx / k.fx)) == pytest.approx(120.0, abs=0.1)
    wide = Perception(k, MOUNT, PerceptionConfig(bearing_span_deg=120.0, scan_bins=124))
    out = wide.process(renderer(intrinsics=k).render((0.0, 0.0, 0.0), person))
    assert len(out.points) > 0
    assert boundary_distance(out.points, person.cylinders[0]).max() <= 0.03
    hit = np.flatnonzero(np.isfinite(out.scan))
    assert np.degrees(wide.bin_angles[hit]).min() > 45.0
    rend = renderer(intrinsics=k, seed=3)
    for theta in (0.0, 1.0, 2.0):
        floor = wide.process(rend.render((0.0, 0.0, theta), Scene(), noise=True))
        assert len(floor.points) == 0 and not floor.unknown.any()
    assert widened_d435(87.0) is D435_848x480
    with pytest.raises(ValueError, match="180"):
        widened_d435(180.0)
