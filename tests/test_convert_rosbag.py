"""`meridian-torch convert rosbag`: ROS 1 and ROS 2 bags written with rosbags' own writers convert back
to the frames and odometry they were made from; bad topics, encodings and timing are named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")

from rosbags.typesys import Stores, get_typestore  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from meridian_torch.cli import app  # noqa: E402
from meridian_torch.config import CONFIG_DIR, load_config  # noqa: E402
from meridian_torch.io.converters.rosbag import RosbagError, convert_rosbag  # noqa: E402
from meridian_torch.io.sequence import SequenceReader, check_sequence  # noqa: E402
from meridian_torch.sim.simulate import simulate_sequence  # noqa: E402

TS = get_typestore(Stores.ROS2_HUMBLE)
T0 = 1.7e9  # Unix time: stamps as a robot records them


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bag") / "seq"
    simulate_sequence(load_config(CONFIG_DIR / "tiny.yaml").sim, out)
    return out


def _header(t: float, frame: str):
    sec = int(np.floor(t))
    return TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9))), frame_id=frame)


CAMERA_FRAME = "camera_color_optical_frame"


def _image(t: float, array: np.ndarray, encoding: str):
    data = np.ascontiguousarray(array).view(np.uint8).reshape(-1)
    return TS.types["sensor_msgs/msg/Image"](header=_header(t, CAMERA_FRAME), height=array.shape[0], width=array.shape[1],
                                              encoding=encoding, is_bigendian=0, step=data.size // array.shape[0],
                                              data=data)


def _odometry(t: float, T: np.ndarray):
    ty = TS.types
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    pose = ty["geometry_msgs/msg/Pose"](position=ty["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                        orientation=ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    zero = ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return ty["nav_msgs/msg/Odometry"](
        header=_header(t, "odom"), child_frame_id="base_link",
        pose=ty["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=ty["geometry_msgs/msg/TwistWithCovariance"](twist=ty["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                          covariance=np.zeros(36)))


def _static_tf(t: float, T_base_camera: np.ndarray):
    """/tf_static: base_link -> camera_link (the mount) -> camera_color_optical_frame (the rotation)."""
    ty = TS.types
    mount = np.eye(4)
    mount[:3, 3] = T_base_camera[:3, 3]
    optical = np.linalg.inv(mount) @ T_base_camera

    def stamped(parent: str, child: str, T: np.ndarray):
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        transform = ty["geometry_msgs/msg/Transform"](
            translation=ty["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=ty["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        return ty["geometry_msgs/msg/TransformStamped"](header=_header(t, parent), child_frame_id=child,
                                                        transform=transform)

    return ty["tf2_msgs/msg/TFMessage"](transforms=[stamped("base_link", "camera_link", mount),
                                                    stamped("camera_link", CAMERA_FRAME, optical)])


def _camera_info(t: float, reader: SequenceReader):
    c = reader.camera
    ty = TS.types
    return ty["sensor_msgs/msg/CameraInfo"](
        header=_header(t, "camera"), height=c.height, width=c.width, distortion_model="plumb_bob", d=np.zeros(5),
        k=np.array([c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1.0]), r=np.eye(3).ravel(),
        p=np.array([c.fx, 0, c.cx, 0, 0, c.fy, c.cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=ty["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def write_bag(path: Path, seq: Path, version: int, *, depth_encoding: str = "16UC1", depth_delay: float = 0.005,
              extra_rgb_topic: bool = False, tf: bool = True) -> None:
    """The tiny sequence as a bag: colour rgb8, depth, camera info, its odometry poses and /tf_static."""
    reader = SequenceReader(seq)
    messages = []
    if tf:
        messages.append(("/tf_static", T0, _static_tf(T0, reader.camera.T_base_camera)))
    for i in range(len(reader)):
        f = reader[i]
        t = T0 + f.timestamp
        messages.append(("/camera/color/image_raw", t, _image(t, f.rgb, "rgb8")))
        if extra_rgb_topic:
            messages.append(("/camera2/color/image_raw", t, _image(t, f.rgb, "rgb8")))
        depth = (np.rint(f.depth * 1000).astype(np.uint16) if depth_encoding == "16UC1"
                 else f.depth.astype(np.float32) if depth_encoding == "32FC1" else f.rgb)
        messages.append(("/camera/aligned_depth_to_color/image_raw", t + depth_delay, _image(t + depth_delay, depth,
                                                                                             depth_encoding)))
        messages.append(("/camera/color/camera_info", t, _camera_info(t, reader)))
    odom = reader.odometry
    for t, T in zip(odom.timestamps, odom.poses):
        messages.append(("/odom", T0 + t, _odometry(T0 + t, T)))
    messages.sort(key=lambda m: m[1])
    if version == 1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), lambda msg, kind: TS.serialize_ros1(msg, kind)
    else:  # 2: ROS 2 with sqlite3 storage, 3: ROS 2 with MCAP storage
        from rosbags.rosbag2 import StoragePlugin, Writer

        storage = StoragePlugin.SQLITE3 if version == 2 else StoragePlugin.MCAP
        writer = Writer(path, version=9, storage_plugin=storage)
        serialize = lambda msg, kind: TS.serialize_cdr(msg, kind)  # noqa: E731
    with writer:
        conns = {}
        for topic, t, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=TS)
            writer.write(conns[topic], int(t * 1e9), serialize(msg, msg.__msgtype__))


@pytest.mark.parametrize("version", [1, 2, 3], ids=["ros1", "ros2-sqlite3", "ros2-mcap"])
@pytest.mark.parametrize("depth_encoding", ["16UC1", "32FC1"])
def test_a_bag_converts_back_to_the_same_frames_and_odometry(tiny: Path, tmp_path: Path, version: int,
                                                             depth_encoding: str) -> None:
    bag = tmp_path / ("rec.bag" if version == 1 else "rec")
    write_bag(bag, tiny, version, depth_encoding=depth_encoding)
    counts = convert_rosbag([bag], tiny / "aerial", tmp_path / "out")
    assert check_sequence(tmp_path / "out") == []
    original, converted = SequenceReader(tiny), SequenceReader(tmp_path / "out")
    assert counts == {"frames": len(original), "unpaired": 0, "without_pose": 0}
    np.testing.assert_allclose(converted.frame_times, original.frame_times + T0, atol=2e-6, rtol=0)
    np.testing.assert_allclose(converted.camera.T_base_camera, original.camera.T_base_camera, atol=1e-9, rtol=0)
    for i in (0, len(original) // 2, len(original) - 1):
        a, b = original[i], converted[i]
        np.testing.assert_array_equal(b.rgb, a.rgb)
        np.testing.assert_allclose(b.depth, np.where(a.depth * 1000 <= 65535, a.depth, 0), atol=5e-4, rtol=0)
        np.testing.assert_allclose(b.T_odom_base, a.T_odom_base, atol=1e-6, rtol=0)


def test_cli_converts_a_bag(tiny: Path, tmp_path: Path) -> None:
    write_bag(tmp_path / "rec.bag", tiny, 1)
    result = CliRunner().invoke(app, ["convert", "rosbag", str(tmp_path / "rec.bag"), "--ortho", str(tiny / "aerial"),
                                      "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "skipped 0 colour images" in result.output


def test_without_tf_static_the_camera_must_be_declared_at_the_base(tiny: Path, tmp_path: Path) -> None:
    from meridian_torch.io.converters.sync import T_BASE_OPTICAL

    write_bag(tmp_path / "rec.bag", tiny, 1, tf=False)
    with pytest.raises(RosbagError, match=r"no static transform chain from the odometry's frame 'base_link' "
                                          r"\(/odom\) to the camera frame 'camera_color_optical_frame'"):
        convert_rosbag([tmp_path / "rec.bag"], tiny / "aerial", tmp_path / "out")
    convert_rosbag([tmp_path / "rec.bag"], tiny / "aerial", tmp_path / "out", camera_at_base=True)
    np.testing.assert_array_equal(SequenceReader(tmp_path / "out").camera.T_base_camera, T_BASE_OPTICAL)


@pytest.mark.parametrize("case", ["missing topic", "ambiguous colour", "unsynchronised", "wrong depth encoding"])
def test_bad_bags_name_the_topic(tiny: Path, tmp_path: Path, case: str) -> None:
    kwargs: dict = {}
    bag = tmp_path / "rec.bag"
    if case == "missing topic":
        write_bag(bag, tiny, 1)
        kwargs["odometry_topic"] = "/wheel_odom"
        match = r"odometry topic '/wheel_odom' is not in the bag; its topics: .*/odom"
    elif case == "ambiguous colour":
        write_bag(bag, tiny, 1, extra_rgb_topic=True)
        match = r"rgb: 2 candidate topics \(/camera/color/image_raw, /camera2/color/image_raw\)"
    elif case == "unsynchronised":
        write_bag(bag, tiny, 1, depth_delay=0.2)
        match = r"/camera/color/image_raw: no colour image has a depth image on .* within 0.02 s"
    else:
        write_bag(bag, tiny, 1, depth_encoding="rgb8")
        match = r"/camera/aligned_depth_to_color/image_raw: depth encoding 'rgb8' not supported"
    with pytest.raises(RosbagError, match=match):
        convert_rosbag([bag], tiny / "aerial", tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()
