"""Camera calibration against rendered truth: floor → height, pitch, roll; ChArUco board →
yaw and x, y; the command end to end on a real pyrealsense2 recording; bad input refused with
the calibration file untouched."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pyrealsense2 as rs
import pytest

from calibration.camera import BoardInput, calibrate_camera
from calibration.charuco import BoardPlacement, BoardSpec
from drivers.depth_source import D435_848x480
from runtime.cli.main import main
from runtime.config.calibration import CameraMount
from runtime.config.settings import load_calibration, render_calibration
from runtime.errors import UserError
from runtime.geometry import R_LINK_OPTICAL, rpy_matrix
from runtime.types import DepthIntrinsics
from sim_stub.depth_render import Box, Cylinder, DepthRenderer, Scene, wall

K = D435_848x480
SPEC = BoardSpec()


def clutter(rng: np.random.Generator, board: BoardPlacement | None = None) -> Scene:
    """People-sized posts, boxes and three walls around open floor; the board as a thin box."""
    cyl = [Cylinder(float(rng.uniform(1.2, 6)), float(rng.uniform(-3, 3)), 0.25, 1.7)
           for _ in range(6)]
    boxes = [Box(float(rng.uniform(1.5, 6)), float(rng.uniform(-3, 3)), 0.6, 0.4,
                 float(rng.uniform(0, 3)), 0.5) for _ in range(4)]
    boxes += [wall(7, -6, 7, 6), wall(-1, 4, 8, 4), wall(-1, -4, 8, -4)]
    if board is not None:
        w, h = SPEC.size_m
        boxes.append(Box(board.x + 0.01, board.y, 0.02, w, math.radians(board.yaw_deg),
                         board.z + h / 2))
    return Scene(cyl, boxes)


def random_mount(rng: np.random.Generator) -> CameraMount:
    """The issue's ranges: 0.25–0.7 m high, pitch −20…+5 deg, roll ±3 deg."""
    return CameraMount((float(rng.uniform(0.0, 0.15)), float(rng.uniform(-0.05, 0.05)),
                        float(rng.uniform(0.25, 0.7))),
                       (float(rng.uniform(-3, 3)), float(rng.uniform(-20, 5)),
                        float(rng.uniform(-5, 5))))


def render_ir(mount: CameraMount, placement: BoardPlacement, rng: np.random.Generator,
              k: DepthIntrinsics = K, px_per_square: int = 60) -> np.ndarray:
    """Left-infrared image of the printed board (white margin) on a textured background: the
    board image is warped by the plane homography at 4x resolution and area-averaged down,
    then blurred and noised."""
    img = SPEC.board().generateImage((SPEC.squares_x * px_per_square,
                                      SPEC.squares_y * px_per_square), marginSize=0)
    m = px_per_square // 2
    img = cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255).astype(np.float32)
    s = SPEC.square_m / px_per_square  # board pixel (u, v) centre -> ((u - m + .5) s, ...)
    to_board = np.array([[s, 0, (0.5 - m) * s], [0, s, (0.5 - m) * s], [0, 0, 1.0]])
    r_base_board, origin = placement.pose_in_base(SPEC)
    r_base_optical = rpy_matrix(*(math.radians(a) for a in mount.rpy_deg)) @ R_LINK_OPTICAL
    r_cb = r_base_optical.T @ r_base_board
    t_cb = r_base_optical.T @ (origin - np.asarray(mount.translation_m))
    cam = np.array([[k.fx, 0, k.cx], [0, k.fy, k.cy], [0, 0, 1.0]])
    ss = 4
    up = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
    hom = up @ cam @ np.column_stack((r_cb[:, 0], r_cb[:, 1], t_cb)) @ to_board
    big = (k.width * ss, k.height * ss)

    def warp(src: np.ndarray) -> np.ndarray:
        out = cv2.warpPerspective(src, hom, big, flags=cv2.INTER_LINEAR)
        return cv2.resize(out, (k.width, k.height), interpolation=cv2.INTER_AREA)

    board, mask = warp(img), warp(np.ones_like(img))
    bg = cv2.GaussianBlur(rng.normal(70, 20, (k.height, k.width)).astype(np.float32), (0, 0), 3)
    out = bg * (1 - mask) + (board * 0.8 + 20) * mask
    out = cv2.GaussianBlur(out, (0, 0), 0.7) + rng.normal(0, 3, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


def board_in_view(mount: CameraMount, rng: np.random.Generator) -> BoardPlacement:
    """A board 0.7–1 m ahead, near the optical axis, turned up to ±15 deg."""
    dist = float(rng.uniform(0.7, 1.0))
    x, y, h = mount.translation_m
    z = h - dist * math.tan(math.radians(mount.rpy_deg[1]))
    return BoardPlacement(x + dist, y + float(rng.uniform(-0.1, 0.1)), z,
                          float(rng.uniform(-15, 15)))


def render_depth(mount: CameraMount, scene: Scene, n: int, seed: int) -> list[np.ndarray]:
    renderer = DepthRenderer(K, mount, seed=seed)
    return [renderer.render((0.0, 0.0, 0.0), scene, noise=True) for _ in range(n)]


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_floor_gives_height_pitch_roll_and_rerenders_the_floor(seed):
    rng = np.random.default_rng(seed)
    truth = random_mount(rng)
    scene = clutter(rng)
    depths = render_depth(truth, scene, 5, seed)
    result = calibrate_camera(depths, K, CameraMount())  # prior: the vendor default
    m = result.mount
    assert abs(m.translation_m[2] - truth.translation_m[2]) < 0.01
    assert abs(m.rpy_deg[1] - truth.rpy_deg[1]) < 0.5
    assert abs(m.rpy_deg[0] - truth.rpy_deg[0]) < 0.5
    # x, y, yaw are not observable from the floor: kept from the prior
    assert m.translation_m[:2] == CameraMount().translation_m[:2] and m.rpy_deg[2] == 0.0
    # rendering with the estimate (and the true yaw, x, y) reproduces the floor pixels
    est = CameraMount(truth.translation_m[:2] + m.translation_m[2:],
                      (*m.rpy_deg[:2], truth.rpy_deg[2]))
    floor_only = Scene([], [])
    z_true = DepthRenderer(K, truth).render_z((0, 0, 0), floor_only)
    z_est = DepthRenderer(K, est).render_z((0, 0, 0), floor_only).copy()
    near = np.isfinite(z_true) & np.isfinite(z_est) & (z_true < 5.0)
    assert near.mean() > 0.02
    assert np.max(np.abs(z_est[near] - z_true[near]) / z_true[near]) < 0.02


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_board_gives_yaw_and_offsets(seed):
    rng = np.random.default_rng(seed)
    truth = random_mount(rng)
    placement = board_in_view(truth, rng)
    depths = render_depth(truth, clutter(rng, placement), 5, seed)
    images = [render_ir(truth, placement, rng) for _ in range(5)]
    result = calibrate_camera(depths, K, CameraMount(),
                              BoardInput(images, K, SPEC, placement))
    m = result.mount
    assert abs(m.rpy_deg[2] - truth.rpy_deg[2]) < 0.5
    assert abs(m.translation_m[0] - truth.translation_m[0]) < 0.01
    assert abs(m.translation_m[1] - truth.translation_m[1]) < 0.01
    assert abs(m.translation_m[2] - truth.translation_m[2]) < 0.01
    assert result.board is not None and result.board.rms_px < 0.5 and not result.warnings()


def test_no_floor_in_view_is_refused():
    mount = CameraMount((0.1, 0.0, 0.5), (0.0, -20.0, 0.0))
    scene = Scene([], [wall(1.0, -5, 1.0, 5, height=4.0)], floor=False)
    with pytest.raises(UserError, match="no floor in view"):
        calibrate_camera(render_depth(mount, scene, 5, 0), K, CameraMount())


def test_board_not_found_is_refused():
    rng = np.random.default_rng(0)
    truth = random_mount(rng)
    placement = board_in_view(truth, rng)
    away = BoardPlacement(placement.x, placement.y + 5.0, placement.z, 0.0)  # out of view
    images = [render_ir(truth, away, rng) for _ in range(5)]
    with pytest.raises(UserError, match="board: the board .* was found in 0 of 5"):
        calibrate_camera(render_depth(truth, clutter(rng), 5, 0), K, CameraMount(),
                         BoardInput(images, K, SPEC, placement))


# --- the command on recordings --------------------------------------------------------------


def write_recording(path: Path, depths: list[np.ndarray], irs: list[np.ndarray] | None) -> None:
    """A real .db3 with a Z16 depth stream and, if given, the left infrared (Y8) stream."""
    intr = rs.intrinsics()
    intr.width, intr.height = K.width, K.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = K.fx, K.fy, K.cx, K.cy
    intr.model, intr.coeffs = rs.distortion.brown_conrady, [0.0] * 5
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")

    def stream(kind, fmt, bpp, uid, index, sensor=sensor):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, index, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = (
            K.width, K.height, 30, bpp, fmt, intr)
        return sensor.add_video_stream(vs).as_video_stream_profile()

    profiles = [(stream(rs.stream.depth, rs.format.z16, 2, 0, 0), 2, depths)]
    if irs is not None:
        profiles.append((stream(rs.stream.infrared, rs.format.y8, 1, 1, 1), 1, irs))
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    recorder = rs.recorder(str(path), dev, False)
    sensor.open([p for p, _, _ in profiles])
    queue = rs.frame_queue(4)
    sensor.start(queue)
    for n in range(len(depths)):
        for profile, bpp, images in profiles:
            f = rs.software_video_frame()
            f.pixels, f.stride, f.bpp = np.ascontiguousarray(images[n]), K.width * bpp, bpp
            f.timestamp, f.domain, f.frame_number = n * 33.3, rs.timestamp_domain.hardware_clock, n
            f.profile = profile
            sensor.on_video_frame(f)
        while queue.poll_for_frame():
            pass
    sensor.stop()
    sensor.close()
    del recorder, queue, profiles, sensor, dev


@pytest.fixture
def cal_file(tmp_path: Path) -> Path:
    path = tmp_path / "robot_calibration.yaml"
    path.write_text(render_calibration(), encoding="utf-8")
    return path


def _run(args: list[str], capsys) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_command_writes_camera_calibration_from_a_recording_with_infrared(tmp_path, cal_file,
                                                                         capsys):
    rng = np.random.default_rng(21)
    truth = random_mount(rng)
    placement = board_in_view(truth, rng)
    depths = render_depth(truth, clutter(rng, placement), 6, 21)
    rec = tmp_path / "calib.db3"
    write_recording(rec, depths, [render_ir(truth, placement, rng) for _ in range(6)])
    before = cal_file.read_text()
    code, out, err = _run(["calibrate", "camera", "--recording", str(rec), "--frames", "6",
                           "--set", f"calibration_file={cal_file}",
                           "--board-pose", *(str(v) for v in (placement.x, placement.y,
                                                              placement.z, placement.yaw_deg))],
                          capsys)
    assert code == 0, err
    cam = load_calibration(cal_file).camera
    assert abs(cam.translation_m[2] - truth.translation_m[2]) < 0.01
    for i in range(3):
        assert abs(cam.rpy_deg[i] - truth.rpy_deg[i]) < 0.5
    for i in range(2):
        assert abs(cam.translation_m[i] - truth.translation_m[i]) < 0.01
    backups = list(tmp_path.glob("robot_calibration.yaml.*.bak"))
    assert len(backups) == 1 and backups[0].read_text() == before
    assert "camera.rpy_deg:" in out and "camera.translation_m:" in out
    report = json.loads(out.strip().splitlines()[-1])
    assert report["written"] == str(cal_file) and report["calibrate"] == "camera"


def test_command_without_board_keeps_xy_yaw_and_says_so(tmp_path, cal_file, capsys):
    rng = np.random.default_rng(22)
    truth = random_mount(rng)
    rec = tmp_path / "depth_only.db3"
    write_recording(rec, render_depth(truth, clutter(rng), 5, 22), None)
    code, out, err = _run(["calibrate", "camera", "--recording", str(rec), "--frames", "5",
                           "--output", str(cal_file)], capsys)
    assert code == 0, err
    assert "translation x, y and yaw kept from the previous calibration" in out
    cam = load_calibration(cal_file).camera
    assert cam.translation_m[:2] == CameraMount().translation_m[:2] and cam.rpy_deg[2] == 0.0
    assert abs(cam.rpy_deg[1] - truth.rpy_deg[1]) < 0.5


@pytest.mark.parametrize(
    ("frames", "extra", "needle"),
    [
        (5, ["--board-pose", "1", "0", "0.5", "0"], "has no infrared stream, which --board needs"),
        (3, [], "the recording ended after 3 depth frames; need 5"),
    ],
)
def test_command_refuses_bad_recordings_and_leaves_the_file(tmp_path, cal_file, capsys, frames,
                                                            extra, needle):
    rng = np.random.default_rng(23)
    rec = tmp_path / "short.db3"
    write_recording(rec, render_depth(random_mount(rng), clutter(rng), frames, 23), None)
    before = cal_file.read_text()
    code, _, err = _run(["calibrate", "camera", "--recording", str(rec), "--frames", "5",
                         "--output", str(cal_file), *extra], capsys)
    assert code == 2 and needle in err and "Traceback" not in err
    assert cal_file.read_text() == before and not list(tmp_path.glob("*.bak"))


def test_command_never_overwrites_the_shipped_default(capsys):
    code, _, err = _run(["calibrate", "camera", "--recording", "missing.db3"], capsys)
    assert code == 2 and "shipped vendor calibration; give --output FILE" in err
