"""The flight recorder (runtime.process.recorder): what a file holds (Foxglove's schemas, every
channel, messages that decode to what the cycle had), rotation and the disk budget, and what a
full queue or a failing disk costs: cycles not recorded (counted) and one log line, never the
robot's cycle."""

from __future__ import annotations

import errno
import json
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from doubles import FreshFeedbackLink, SimClock
from flight_records import episode_records, wait_written
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.reader import make_reader
from rooms import write_room

from runtime.config.settings import RecorderConfig, load_config
from runtime.process.cycle_record import CycleRecord
from runtime.process.recorder import Recorder, recording_directory, recording_metadata
from runtime.types import DepthFrame, DepthIntrinsics

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def records() -> list[CycleRecord]:
    return episode_records(60)


def recorder(tmp_path: Path, **cfg) -> Recorder:
    loaded = load_config(None, [])
    return Recorder(tmp_path, RecorderConfig(**cfg), loaded.calibration.camera,
                    loaded.config.perception.decimation, {"test": "yes"})


def read(path: Path) -> tuple[dict, dict[str, list]]:
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        messages: dict[str, list] = {}
        for _schema, channel, message in reader.iter_messages():
            messages.setdefault(channel.topic, []).append(message.data)
    return schemas, messages


def test_starting_leaves_other_files_in_the_directory_alone(tmp_path):
    """`eval --jobs 2 --record DIR` starts two recorders in one directory at once: one's
    write probe must not be another's (a shared probe name, removed by the first, failed the
    second's start and lost the evaluation)."""
    others = {name: tmp_path / name for name in (".write-probe", ".probe", "a.mcap")}
    for path in others.values():
        path.write_bytes(b"another recorder's")
    rec = recorder(tmp_path)
    rec.start()
    rec.stop()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(others)
    assert all(p.read_bytes() == b"another recorder's" for p in others.values())


def test_a_file_holds_every_channel_in_foxglove_schemas(tmp_path, records):
    rec = recorder(tmp_path, full_depth_every=5)
    rec.start()
    for i, r in enumerate(records):
        rec.offer(r)
        wait_written(rec, i + 1)  # as at 20 Hz: the writer keeps up between cycles
    rec.stop()
    assert rec.stopped_reason is None and rec.counts["dropped"] == 0
    [path] = tmp_path.glob("safemove-*.mcap")
    schemas, messages = read(path)
    assert schemas == {"foxglove.FrameTransform": "protobuf", "foxglove.RawImage": "protobuf",
                       "foxglove.PointCloud": "protobuf", "foxglove.SceneUpdate": "protobuf",
                       "safemove.Cycle": "jsonschema"}
    perceived = [r for r in records if r.perceived is not None]
    assert len(messages["/tf"]) == len(messages["/cycle"]) == len(records)
    assert len(messages["/tf_static"]) == 1
    assert len(messages["/camera/depth_decimated"]) == len(perceived)
    assert len(messages["/camera/depth"]) == -(-len(perceived) // 5)
    # the decimated image is exactly the pixels the world model read
    first = perceived[0].perceived
    assert first is not None
    d = load_config(None, []).config.perception.decimation
    img = RawImage.FromString(messages["/camera/depth_decimated"][0])
    pixels = np.frombuffer(img.data, dtype="<u2").reshape(img.height, img.width)
    np.testing.assert_array_equal(pixels, first.depth[::d, ::d])
    assert img.encoding == "16UC1" and img.frame_id == "camera_depth_optical"
    cloud = PointCloud.FromString(messages["/obstacles"][0])
    assert cloud.point_stride == 12 and len(cloud.data) == 12 * len(
        perceived[0].result.world.points_base)
    # the cycle's decisions, as the cycle made them
    cycles = [json.loads(m) for m in messages["/cycle"]]
    for r, c in zip(records, cycles):
        assert c["t"] == r.t and c["command"] == {"v": r.result.command.v,
                                                  "omega": r.result.command.omega}
        assert len(c["increments"]) == len(r.increments)
    decided = [c for c in cycles if c["dwa"] is not None]
    assert decided and all(c["shield"]["kind"] in ("passed", "replaced", "turned", "braked")
                           for c in decided)
    scenes = [SceneUpdate.FromString(m) for m in messages["/planning"]]
    assert any(e.id == "plan" and e.lines for s in scenes for e in s.entities)


def test_files_rotate_by_size_and_the_oldest_go_to_stay_in_budget(tmp_path, records):
    rec = recorder(tmp_path, file_max_mb=0.2, total_max_mb=0.6, full_depth_every=1)
    rec.start()
    for i, r in enumerate(records * 3):
        rec.offer(r)
        wait_written(rec, i + 1)  # the writer keeps up: this test is about files, not drops
    rec.stop()
    kept = sorted(tmp_path.glob("safemove-*.mcap"))
    assert rec.counts["files"] > 3 and rec.counts["deleted"] > 0, rec.summary()
    assert sum(p.stat().st_size for p in kept) <= 0.6e6 + 0.25e6  # + the file being written
    for p in kept:  # every file kept is whole: readable to its summary
        _schemas, messages = read(p)
        assert "/tf_static" in messages and "/cycle" in messages


def test_a_full_disk_stops_recording_with_one_line_and_drops_the_rest(tmp_path, records,
                                                                      caplog, monkeypatch):
    rec = recorder(tmp_path)
    real_open = open

    class FullDisk:
        """A file on a disk that fills after 100 kB (ENOSPC), as a tiny tmpfs would."""

        def __init__(self, *args, **kwargs) -> None:
            self._f = real_open(*args, **kwargs)

        def write(self, data) -> int:
            if self._f.tell() + len(data) > 100_000:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return self._f.write(data)

        def __getattr__(self, name):
            return getattr(self._f, name)

    monkeypatch.setattr("runtime.process.recorder.open", FullDisk, raising=False)
    caplog.set_level(logging.INFO, "safemove.recorder")
    rec.start()
    for i, r in enumerate(records):
        rec.offer(r)
        wait_written(rec, i + 1)
    rec.stop()
    assert rec.stopped_reason is not None and "No space left on device" in rec.stopped_reason
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "recording stopped (the robot goes on)" in errors[0].message
    assert rec.counts["cycles"] + rec.counts["dropped"] < len(records) + 1
    rec.offer(records[0])  # after it stopped: counted, nothing else
    assert rec.counts["dropped"] >= 1


def test_a_full_queue_drops_cycles_instead_of_waiting(tmp_path, records):
    rec = recorder(tmp_path, queue_cycles=3)
    # not started: nothing writes, so the queue fills and the rest are dropped at once
    for r in records[:10]:
        rec.offer(r)
    assert rec.counts["dropped"] == 7 and len(rec._queue) == 3


def test_recording_directory_from_config_then_systemd_logs_directory(monkeypatch):
    monkeypatch.delenv("LOGS_DIRECTORY", raising=False)
    assert recording_directory(RecorderConfig()) is None
    monkeypatch.setenv("LOGS_DIRECTORY", "/var/log/safemove")
    assert recording_directory(RecorderConfig()) == Path("/var/log/safemove/recordings")
    assert recording_directory(RecorderConfig(directory="/data/rec")) == Path("/data/rec")


def test_an_unwritable_directory_refuses_the_start_in_one_line(tmp_path, capsys):
    from runtime.cli.main import main

    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = main(["drive", "--twist", "0", "0", "--duration", "1",
                 "--set", f"recorder.directory={blocker}/rec", "--set", "base.port=/nonexistent"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "recorder.directory" in err[0], err


@pytest.mark.hil
@pytest.mark.timeout(300)
def test_a_demo_whose_disk_fills_mid_run_reaches_its_goal(tmp_path):
    """A real process whose files may not grow past 2 MB (RLIMIT_FSIZE: the kernel refuses the
    write as a full disk would): the recording stops with one line, the robot drives on to
    the goal. A room without people and a goal 5 m away, reached in 26-38 s with 120 s
    allowed, so the outcome is the recorder's and not the machine's load (a crowd in real
    time is not repeatable)."""
    import resource

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG from write(), not a kill
        resource.setrlimit(resource.RLIMIT_FSIZE, (2_000_000, 2_000_000))

    room = write_room(tmp_path, "long_room", goal=(2.5, 0.0), time_limit_s=120.0,
                      start=(-2.5, -2.4, -0.05, 0.05), obstacles=(
                          "\n  - {type: cylinder, center: [0.0, 1.2], radius: 0.3, height: 1.0}"
                          "\n  - {type: box, center: [1.0, -1.2], size: [0.6, 0.6], yaw_deg: 0.0,"
                          " height: 0.8}\n"))
    out = subprocess.run(
        [sys.executable, "-m", "runtime.cli.main", "demo", "--planner", "dwa", "--scenario", room,
         "--record", str(tmp_path / "rec"), "--set", "recorder.full_depth_every=1"],
        check=False, capture_output=True, text=True, timeout=280, preexec_fn=small_files,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["world"]["status"] == "success"
    stopped = [line for line in out.stderr.splitlines() if "recording stopped" in line]
    assert len(stopped) == 1 and "File too large" in stopped[0], stopped
    assert report["link"]["recorder"]["stopped"] is not None
    assert "Traceback" not in out.stderr


@pytest.mark.sim
def test_eval_records_each_episode_and_the_recording_replays(tmp_path, capsys):
    """`eval --record`: one file per episode, named for it; the lock-stepped episode (no
    clock: budgets are counts) replays bit for bit."""
    from runtime.cli.main import main
    from runtime.process.replay import replay

    assert main(["eval", "--planner", "dwa", "--scenarios", "paper_a", "--episodes", "1",
                 "--seed", "6", "--record", str(tmp_path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    [log] = tmp_path.glob("paper_a-seed6-*.mcap")
    replayed = replay(log)
    assert replayed["cycles"] == result["episodes"][0]["cycles"]
    assert replayed["differing_commands"] == 0


class SlowCamera:
    """Unit-test double: a 15 fps camera on the loop's clock seeing open floor 3 m ahead."""

    K = DepthIntrinsics(848, 480, 420.0, 420.0, 424.0, 240.0)

    def __init__(self, clock: SimClock) -> None:
        self._clock = clock
        self._last: float | None = None
        self.sent = 0

    def poll(self) -> DepthFrame | None:
        now = self._clock()
        if self._last is not None and now - self._last < 1.0 / 15.0:
            return None
        self._last = now
        self.sent += 1
        return DepthFrame(np.full((480, 848), 3000, np.uint16), now, self.sent, self.K)


def recorded_run(tmp_path: Path, job, recorder_cls: type[Recorder] = Recorder,
                 handoff=None, clock: SimClock | None = None,
                 link: FreshFeedbackLink | None = None) -> Path:
    """12 cycles of the loop on simulated time with `job`, recorded: the one file."""
    from runtime.process.loop import ControlLoop
    from runtime.process.sdnotify import SystemdNotifier

    loaded = load_config(None, [])
    clock = clock or SimClock()
    rec = recorder_cls(tmp_path, RecorderConfig(), loaded.calibration.camera,
                       loaded.config.perception.decimation, recording_metadata(loaded, job))
    loop = ControlLoop(loaded.config, loaded.calibration, link or FreshFeedbackLink(clock), job,
                       SystemdNotifier(None), clock=clock, max_cycles=12,
                       depth=SlowCamera(clock), wait=clock.wait, control=handoff, recorder=rec)
    rec.start()
    loop.run()
    rec.stop()
    [path] = tmp_path.glob("safemove-*.mcap")
    return path


def dwa_job():
    from runtime.jobs.dwa import DWAJob

    return DWAJob((2.0, 0.0), load_config(None, []).config, None)


def mission_job(handoff, clock=None):
    """The service's job; its DWA budgets on `clock` (None: counts, as lock-stepped)."""
    from runtime.jobs.dwa import DWAJob
    from runtime.jobs.mission import MissionJob

    cfg = load_config(None, []).config
    return MissionJob(cfg.control, "dwa",
                      lambda goal, tol, speed: DWAJob(goal, cfg, clock, arrival_radius_m=tol,
                                                      speed_limit=speed),
                      handoff.post_event)


def test_a_frame_taken_before_the_first_cycle_is_recorded_with_it(tmp_path):
    """The loop's start-up admits the first frame before any cycle runs (INIT waits for it);
    the first cycle, which plans on it, records it, so the recording replays from cycle 0."""
    from runtime.process.replay import replay

    path = recorded_run(tmp_path, dwa_job())
    first = json.loads(read(path)[1]["/cycle"][0])
    assert [f["frame_number"] for f in first["frames"]] == [1]  # taken during start-up
    assert first["perceived"] == 1 and first["command"]["v"] > 0
    result = replay(path)
    assert (result["cycles"], result["differing_commands"]) == (12, 0), result


def test_a_goal_given_during_start_up_is_replayed_before_the_first_cycle(tmp_path):
    """The service takes a goal while it waits for its inputs (INIT); the recording carries
    that pass of the control socket with the first cycle, so the replay starts as the robot
    did: already navigating."""
    from runtime.control.protocol import Request, Waypoint
    from runtime.process.control_server import ControlHandoff
    from runtime.process.replay import replay

    handoff = ControlHandoff()
    handoff.commands.append((7, Request("goal", "g", (Waypoint(2.0, 0.0),))))
    path = recorded_run(tmp_path, mission_job(handoff), handoff=handoff)
    first = json.loads(read(path)[1]["/cycle"][0])
    [init] = first["startup_control"]
    assert init["hold"].startswith("INIT") and init["commands"][0]["request"]["type"] == "goal"
    assert first["command"]["v"] > 0  # the first cycle already drove toward the goal
    result = replay(path)
    assert (result["cycles"], result["differing_commands"]) == (12, 0), result


class BusyClock(SimClock):
    """Unit-test double: simulated time that moves on at every reading, as on a loaded
    machine, so the DWA's and the shield's time budgets cut their work short."""

    def __call__(self) -> float:
        self.now += 0.0005
        return self.now


class CancelsWhileDriving(FreshFeedbackLink):
    """Unit-test double: a client's cancel reaches the control socket while the base takes
    the `at`-th command that moves the robot."""

    def __init__(self, clock, handoff, at: int) -> None:
        super().__init__(clock)
        self._handoff, self._at = handoff, at

    def set_command(self, twist, now: float) -> None:
        super().set_command(twist, now)
        if sum(c.v > 0 for c in self.commands) == self._at and twist.v > 0:
            from runtime.control.protocol import Request

            self._handoff.commands.append((7, Request("cancel", "c")))


def test_the_cycle_a_cancel_follows_records_the_decision_of_the_planner_that_drove_it(
        tmp_path):
    """A cancel (or a new goal) applied after a cycle drops that cycle's planner; the record
    still carries the dropped planner's budgets and shield decision, so the replay repeats
    the cycle as it ran, budgets cut short included (on a loaded machine they are)."""
    from runtime.control.protocol import Request, Waypoint
    from runtime.process.control_server import ControlHandoff
    from runtime.process.replay import replay

    handoff = ControlHandoff()
    handoff.commands.append((7, Request("goal", "g", (Waypoint(2.0, 0.0),))))
    clock = BusyClock()
    path = recorded_run(tmp_path, mission_job(handoff, clock), handoff=handoff, clock=clock,
                        link=CancelsWhileDriving(clock, handoff, at=6))
    cycles = [json.loads(m) for m in read(path)[1]["/cycle"]]
    [cancelled] = [c for c in cycles
                   if any(a["request"]["type"] == "cancel" for a in c["commands"])]
    assert cancelled["command"]["v"] > 0 and cancelled["shield"] is not None
    assert cancelled["budgets"]["dwa"][1], cancelled["budgets"]  # the busy clock cut it
    result = replay(path)
    assert (result["cycles"], result["differing_commands"],
            result["differing_shield_decisions"]) == (12, 0, 0), result


class DropsCycle(Recorder):
    """Unit-test double: a recorder whose queue was full when cycle `drop` was offered."""

    drop = 5

    def offer(self, record: CycleRecord) -> None:
        if self._offered == self.drop:
            self._offered += 1
            self.counts["dropped"] += 1
            return
        super().offer(record)


def test_a_replay_stops_where_the_recorder_dropped_cycles(tmp_path, caplog):
    """Each cycle carries its number in the run; the cycles after a gap cannot be compared
    (their predecessors' inputs are gone): the replay says so and stops there."""
    from runtime.process.replay import replay

    path = recorded_run(tmp_path, dwa_job(), DropsCycle)
    seqs = [json.loads(m)["seq"] for m in read(path)[1]["/cycle"]]
    assert seqs == [0, 1, 2, 3, 4, *range(6, 12)]
    caplog.set_level("WARNING", logger="safemove.replay")
    result = replay(path)
    assert result["gap"] == {"after_cycle": 5, "missing": 1}
    assert (result["cycles"], result["differing_commands"]) == (5, 0)
    assert result["first_cycle_of_run"] == 0
    assert any("dropped 1 cycles after cycle 5" in r.getMessage() for r in caplog.records)
