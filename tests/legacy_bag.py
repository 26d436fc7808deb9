"""Test helper: write a legacy RealSense ROS 1 `.bag` (file format v3) holding one Z16 depth stream.

pyrealsense2 2.59 can only *write* rosbag2 `.db3`, but still *reads* the ROS 1 `.bag` files that
realsense-viewer and older SDKs wrote (it picks the reader by extension). To test that path we
write such a bag ourselves with `rosbags.rosbag1.Writer`, following what librealsense's ROS 1
reader expects (IntelRealSense/librealsense: src/media/ros/ros_reader.cpp, ros_file_format.h,
ros_writer.cpp, and the generated message headers under
third-party/realsense-file/rosbag/msgs/, e.g. realsense_msgs/StreamInfo.h, sensor_msgs/Image.h):

* `/file_version` (std_msgs/UInt32): the reader accepts 2 and up; 3 is the first version whose
  options are `/option/<name>/value` Float32 topics, and below 4 no processing-block topic is
  needed.
* Static description, all stamped `ros::TIME_MIN` (0 s, 1 ns), because the reader reads the
  options with a view from TIME_MIN to TIME_MIN and starts streaming at TIME_MIN + 1 ns (bag
  time 0 is worse: librealsense's rosbag drops such index entries as "invalid time"):
  `/device_0/info` and `/device_0/sensor_0/info` (diagnostic_msgs/KeyValue, keys are
  rs2_camera_info names), `/device_0/sensor_0/Depth_0/info` (realsense_msgs/StreamInfo: fps,
  encoding "mono16" = Z16, is_recommended), `/device_0/sensor_0/Depth_0/info/camera_info`
  (sensor_msgs/CameraInfo: width, height, K = fx 0 ppx 0 fy ppy 0 0 1, distortion_model an
  rs2_distortion name, D), `/device_0/sensor_0/Depth_0/tf/0` (geometry_msgs/Transform, the
  extrinsics to reference group 0), `/device_0/sensor_0/option/Depth Units/value`
  (std_msgs/Float32) and `.../description` (std_msgs/String).
* Each frame: `/device_0/sensor_0/Depth_0/image/data` (sensor_msgs/Image, "mono16", step 2*width,
  little endian). The reader takes the frame number from `header.seq` and the timestamp from
  `header.stamp` (seconds, reported in ms); the bag time only orders messages. Its
  `/device_0/sensor_0/Depth_0/image/metadata` KeyValue messages are found by having exactly the
  same bag time: `timestamp_domain`, `system_time`, and rs2_frame_metadata names.

Message md5sums must match the ones compiled into librealsense (its rosbag checks them on
`isType`/`instantiate`); rosbags derives them from the canonical ROS 1 (noetic) definitions, and the
one custom type, realsense_msgs/StreamInfo, is registered here from its .msg text
(md5 311d7e24eac31bb87271d041bf70ff7d).
"""

from __future__ import annotations

import os

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from runtime.types import DepthIntrinsics

FILE_VERSION = 3
TIME_MIN_NS = 1  # ros::TIME_MIN = Time(0, 1): where the SDK puts the static description
FIRST_FRAME_NS = 1_000_000  # bag time of the first frame (any time after TIME_MIN + 1 ns works)

STREAM_INFO_MSG = "uint32 fps\nstring encoding\nbool is_recommended\n"
STREAM_INFO_MD5 = "311d7e24eac31bb87271d041bf70ff7d"

_DEVICE = "/device_0"
_SENSOR = f"{_DEVICE}/sensor_0"
_STREAM = f"{_SENSOR}/Depth_0"


def _typestore():
    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return ts


def _stamp(ts, ns: int):
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                                   nanosec=ns % 1_000_000_000)


def write_legacy_depth_bag(
    path: str | os.PathLike,
    frames: list[tuple[np.ndarray, float, int]],
    intrinsics: DepthIntrinsics,
    fps: int,
) -> None:
    """Write `frames` ((HxW uint16 depth, t_ms, frame_number), in time order) to a new ROS 1 bag.

    Played back, frame i has frame number frame_number (header.seq), timestamp t_ms (header.stamp,
    to the nanosecond) and depth scale intrinsics.depth_unit_m (as float32, the option's type).
    """
    ts = _typestore()
    T = ts.types
    k = intrinsics
    if not frames:
        raise ValueError("a recording needs at least one frame")
    t0_ms = frames[0][1]

    with Writer(os.fspath(path)) as bag:
        conns: dict[str, object] = {}

        def put(topic: str, msgtype: str, msg, time_ns: int) -> None:
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=ts)
            bag.write(conns[topic], time_ns, ts.serialize_ros1(msg, msgtype))

        def key_value(topic: str, key: str, value: str, time_ns: int) -> None:
            put(topic, "diagnostic_msgs/msg/KeyValue",
                T["diagnostic_msgs/msg/KeyValue"](key=key, value=value), time_ns)

        # -- static description at TIME_MIN ------------------------------------------------
        put("/file_version", "std_msgs/msg/UInt32", T["std_msgs/msg/UInt32"](data=FILE_VERSION),
            TIME_MIN_NS)
        for key, value in (("Name", "SafeMove synthetic depth"), ("Serial Number", "0"),
                           ("Firmware Version", "0.0.0.0")):
            key_value(f"{_DEVICE}/info", key, value, TIME_MIN_NS)
        key_value(f"{_SENSOR}/info", "Name", "Stereo Module", TIME_MIN_NS)
        put(f"{_STREAM}/info", "realsense_msgs/msg/StreamInfo",
            T["realsense_msgs/msg/StreamInfo"](fps=int(fps), encoding="mono16",
                                               is_recommended=True), TIME_MIN_NS)
        header0 = T["std_msgs/msg/Header"](seq=0, stamp=_stamp(ts, 0), frame_id="")
        camera_matrix = np.array([k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0])
        put(f"{_STREAM}/info/camera_info", "sensor_msgs/msg/CameraInfo",
            T["sensor_msgs/msg/CameraInfo"](
                header=header0, height=k.height, width=k.width,
                distortion_model="Brown Conrady", D=np.zeros(5), K=camera_matrix,
                R=np.eye(3).ravel(), P=np.zeros(12), binning_x=0, binning_y=0,
                roi=T["sensor_msgs/msg/RegionOfInterest"](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)),
            TIME_MIN_NS)
        put(f"{_STREAM}/tf/0", "geometry_msgs/msg/Transform",
            T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            TIME_MIN_NS)
        put(f"{_SENSOR}/option/Depth Units/value", "std_msgs/msg/Float32",
            T["std_msgs/msg/Float32"](data=float(k.depth_unit_m)), TIME_MIN_NS)
        put(f"{_SENSOR}/option/Depth Units/description", "std_msgs/msg/String",
            T["std_msgs/msg/String"](data="Number of meters represented by a single depth unit"),
            TIME_MIN_NS)

        # -- frames -------------------------------------------------------------------------
        last_ns = -1
        for depth, t_ms, frame_number in frames:
            if depth.dtype != np.uint16 or depth.shape != (k.height, k.width):
                raise ValueError(f"depth must be uint16 {(k.height, k.width)}, got "
                                 f"{depth.dtype} {depth.shape}")
            if t_ms < 0:
                raise ValueError("header.stamp cannot hold a negative timestamp")
            bag_ns = FIRST_FRAME_NS + round((t_ms - t0_ms) * 1e6)
            if bag_ns <= last_ns:  # metadata is matched to its image by identical bag time
                raise ValueError("frame timestamps must be strictly increasing")
            last_ns = bag_ns
            header = T["std_msgs/msg/Header"](seq=int(frame_number),
                                              stamp=_stamp(ts, round(t_ms * 1e6)), frame_id="")
            data = np.ascontiguousarray(depth, dtype="<u2").view(np.uint8).ravel()
            put(f"{_STREAM}/image/data", "sensor_msgs/msg/Image",
                T["sensor_msgs/msg/Image"](header=header, height=k.height, width=k.width,
                                           encoding="mono16", is_bigendian=0,
                                           step=2 * k.width, data=data), bag_ns)
            for key, value in (("timestamp_domain", "Hardware Clock"), ("system_time", "0"),
                               ("Frame Counter", str(int(frame_number))),
                               ("Frame Timestamp", str(round(t_ms * 1000.0)))):
                key_value(f"{_STREAM}/image/metadata", key, value, bag_ns)
