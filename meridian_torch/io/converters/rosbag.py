"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP storage) -> the sequence folder format (README, Formats),
read with the `rosbags` library (no ROS installation).

Topics: a colour image (sensor_msgs/Image rgb8, bgr8, rgba8, bgra8, mono8, or CompressedImage
jpeg/png), a depth image (sensor_msgs/Image 16UC1 in millimetres or 32FC1 in metres), the
colour camera's sensor_msgs/CameraInfo and nav_msgs/Odometry (T_odom_base: the pose of
child_frame_id in frame_id). Each is found by message type when not named; two candidates are
an error naming them. Times are the messages' header stamps. Each colour image is paired with
the depth image nearest in time within `max_dt_s` (the depth must be registered to the colour
camera, as RealSense/ZED `aligned_depth_to_color` topics are); colour images without depth or
outside the odometry's time span are skipped and counted.

T_base_camera: the static TF chain (/tf_static) from the odometry's child frame to the colour
image's frame; a bag without that chain is refused unless `camera_at_base` puts the base at the
camera (x forward, z up), which is right only for a level camera. Two passes over the bag, the
second holding only the frames waiting for their partner: memory stays bounded.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import closing
from pathlib import Path

import cv2
import numpy as np

from meridian_torch.errors import MeridianError
from meridian_torch.geometry.se3 import quat_xyzw_to_matrix
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.converters.sync import T_BASE_OPTICAL, associate, undistort_maps
from meridian_torch.io.ortho import read_orthophoto
from meridian_torch.io.sequence import SequenceWriter

__all__ = ["RosbagError", "convert_rosbag"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
COLOUR_ENCODINGS = {"rgb8": cv2.COLOR_RGB2BGR, "bgr8": None, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR,
                    "mono8": cv2.COLOR_GRAY2BGR}
DEPTH_ENCODINGS = {"16UC1": 1000.0, "mono16": 1000.0, "32FC1": 1.0}  # units per metre
DEPTH_SCALE = 1000.0  # written depth PNGs: millimetres


class RosbagError(MeridianError):
    """A bag, topic or message that cannot be converted (the message names it)."""


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _pick(connections, msgtypes: tuple[str, ...], topic: str | None, what: str,
          keep: Callable[[str], bool] = lambda name: True, prefer: Callable[[str], bool] = lambda name: False) -> str:
    """The topic of `what`: the one named, else the only one of these message types whose name
    `keep` accepts (several: the only one `prefer` picks)."""
    topics = {c.topic: c.msgtype for c in connections}
    if topic is not None:
        if topic not in topics:
            raise RosbagError(f"{what} topic {topic!r} is not in the bag; its topics: {', '.join(sorted(topics))}")
        if topics[topic] not in msgtypes:
            raise RosbagError(f"{what} topic {topic!r} carries {topics[topic]}, expected {' or '.join(msgtypes)}")
        return topic
    candidates = sorted(t for t, m in topics.items() if m in msgtypes and keep(t.lower()))
    if len(candidates) > 1:
        candidates = [t for t in candidates if prefer(t.lower())] or candidates
    if len(candidates) != 1:
        found = ", ".join(candidates) if candidates else "none"
        raise RosbagError(f"{what}: {len(candidates)} candidate topics ({found}); name one with --{what}-topic")
    return candidates[0]


def _colour(msg, msgtype: str, topic: str) -> np.ndarray:
    """BGR uint8 image of a colour message."""
    if msgtype == COMPRESSED:
        image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise RosbagError(f"{topic}: compressed image in format {msg.format!r} could not be decoded")
        return image
    if msg.encoding not in COLOUR_ENCODINGS:
        raise RosbagError(f"{topic}: colour encoding {msg.encoding!r} not supported ({', '.join(COLOUR_ENCODINGS)})")
    channels = {"mono8": 1, "rgb8": 3, "bgr8": 3}.get(msg.encoding, 4)
    rows = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)
    image = np.ascontiguousarray(rows[:, : msg.width * channels].reshape(msg.height, msg.width, channels))
    code = COLOUR_ENCODINGS[msg.encoding]
    return image if code is None else cv2.cvtColor(image, code)


def _depth_m(msg, topic: str) -> np.ndarray:
    """Depth in metres (0 = none) of a depth message."""
    if msg.encoding not in DEPTH_ENCODINGS:
        raise RosbagError(f"{topic}: depth encoding {msg.encoding!r} not supported (16UC1 millimetres, 32FC1 metres)")
    dtype = np.dtype(np.float32 if msg.encoding == "32FC1" else np.uint16)
    dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)
    values = rows[:, : msg.width * dtype.itemsize].copy().view(dtype).reshape(msg.height, msg.width)
    depth = values.astype(np.float64) / DEPTH_ENCODINGS[msg.encoding]
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)


def _matrix(p, q) -> np.ndarray:
    """(4, 4) from a position/translation and a quaternion message."""
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix([q.x, q.y, q.z, q.w])
    T[:3, 3] = [p.x, p.y, p.z]
    return T


def _pose(msg) -> np.ndarray:
    return _matrix(msg.pose.pose.position, msg.pose.pose.orientation)


def _chain(edges: dict[tuple[str, str], np.ndarray], source: str, target: str) -> np.ndarray | None:
    """T_source_target through the static transforms (T_parent_child per edge, walked both ways)."""
    links: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (parent, child), T in edges.items():
        links.setdefault(parent, []).append((child, T))
        links.setdefault(child, []).append((parent, np.linalg.inv(T)))
    found = {source: np.eye(4)}
    queue = [source]
    while queue:
        frame = queue.pop(0)
        for other, T in links.get(frame, []):
            if other not in found:
                found[other] = found[frame] @ T
                queue.append(other)
    return found.get(target)


def convert_rosbag(
    bags: Sequence[Path],
    ortho: Path,
    out: Path,
    *,
    rgb_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    odometry_topic: str | None = None,
    camera_at_base: bool = False,
    max_dt_s: float = 0.02,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, int]:
    """Write the sequence folder `out` from one recording (a ROS 1 .bag, ROS 2 bag folder or split
    bags); returns counts of frames written and colour images skipped."""
    from rosbags.highlevel import AnyReader

    if not max_dt_s > 0:
        raise RosbagError(f"max_dt_s must be positive, got {max_dt_s}")
    for bag in bags:
        if not bag.exists():
            raise RosbagError(f"{bag}: not found")
    SequenceWriter.check_target(out, overwrite)
    aerial = read_orthophoto(ortho)
    try:
        reader = AnyReader([Path(b) for b in bags])
        reader.open()
    except Exception as exc:  # rosbags raises its own error types per format
        raise RosbagError(f"{', '.join(map(str, bags))}: not a readable ROS bag ({exc})") from None
    with closing(reader):
        conns = reader.connections
        rgb_t = _pick(conns, (IMAGE, COMPRESSED), rgb_topic, "rgb", keep=lambda n: "depth" not in n,
                      prefer=lambda n: "color" in n or "rgb" in n)
        depth_t = _pick(conns, (IMAGE,), depth_topic, "depth", keep=lambda n: "depth" in n,
                        prefer=lambda n: "aligned" in n or "registered" in n)
        namespace = rgb_t.rsplit("/", 1)[0].lower()
        info_t = _pick(conns, (CAMERA_INFO,), camera_info_topic, "camera-info", prefer=lambda n: n.startswith(namespace))
        odom_t = _pick(conns, (ODOMETRY,), odometry_topic, "odometry")
        by_topic = {c.topic: c for c in conns}

        # Pass 1: stamps, odometry and the camera model (nothing large is kept).
        stamps: dict[str, list[float]] = {rgb_t: [], depth_t: []}
        odom_times, odom_poses, info = [], [], None
        frames = {"base": None, "camera": None}
        static: dict[tuple[str, str], np.ndarray] = {}
        tf_static = [c for c in conns if c.topic == "/tf_static" and c.msgtype == TF]
        wanted = [by_topic[t] for t in (rgb_t, depth_t, info_t, odom_t)] + tf_static
        for conn, _, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == TF:
                for tf in msg.transforms:
                    static[(tf.header.frame_id.lstrip("/"), tf.child_frame_id.lstrip("/"))] = _matrix(
                        tf.transform.translation, tf.transform.rotation)
            elif conn.topic == odom_t:
                odom_times.append(_stamp(msg))
                odom_poses.append(_pose(msg))
                frames["base"] = frames["base"] or msg.child_frame_id.lstrip("/")
            elif conn.topic == info_t:
                info = info or msg
            else:
                stamps[conn.topic].append(_stamp(msg))
                if conn.topic == rgb_t:
                    frames["camera"] = frames["camera"] or msg.header.frame_id.lstrip("/")
        if info is None:
            raise RosbagError(f"{info_t}: no CameraInfo message")
        if len(odom_times) < 2:
            raise RosbagError(f"{odom_t}: {len(odom_times)} odometry messages, at least 2 are needed")
        order = np.argsort(odom_times, kind="stable")
        odometry = Trajectory(np.asarray(odom_times)[order], np.stack(odom_poses)[order])
        rgb_times, depth_times = np.asarray(stamps[rgb_t]), np.asarray(stamps[depth_t])
        if len(rgb_times) == 0 or len(depth_times) == 0:
            raise RosbagError(f"{rgb_t if len(rgb_times) == 0 else depth_t}: no messages")
        if np.any(np.diff(rgb_times) <= 0) or np.any(np.diff(depth_times) < 0):
            raise RosbagError(f"{rgb_t} / {depth_t}: header stamps are not increasing in bag order")
        pair = associate(rgb_times, depth_times, max_dt_s)
        covered = (rgb_times >= odometry.timestamps[0]) & (rgb_times <= odometry.timestamps[-1])
        use = np.flatnonzero((pair >= 0) & covered)
        if len(use) == 0:
            raise RosbagError(f"{rgb_t}: no colour image has a depth image on {depth_t} within {max_dt_s} s "
                              f"and odometry on {odom_t}")
        T_base_camera = _chain(static, frames["base"] or "", frames["camera"] or "")
        at_base = T_base_camera is None
        if at_base:
            if not camera_at_base:
                raise RosbagError(
                    f"no static transform chain from the odometry's frame {frames['base']!r} ({odom_t}) to the camera "
                    f"frame {frames['camera']!r} ({rgb_t}) in /tf_static; record it, or pass --camera-at-base for a "
                    "level camera at the base"
                )
            T_base_camera = T_BASE_OPTICAL
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        camera = CameraModel(int(info.width), int(info.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], DEPTH_SCALE,
                             T_base_camera)
        maps = undistort_maps(K, info.d, camera.width, camera.height) if info.distortion_model in ("plumb_bob",
                                                                                                   "rational_polynomial") else None

        # Pass 2: frames in colour order; a frame waits only for its depth partner.
        wanted_rgb = {int(i): k for k, i in enumerate(use)}
        wanted_depth = {int(pair[i]): k for k, i in enumerate(use)}
        colour: dict[int, np.ndarray] = {}
        depth: dict[int, np.ndarray] = {}
        seen = {rgb_t: 0, depth_t: 0}
        written = 0
        with SequenceWriter(out, camera, overwrite=overwrite) as writer:
            for conn, _, raw in reader.messages(connections=[by_topic[rgb_t], by_topic[depth_t]]):
                index = seen[conn.topic]
                seen[conn.topic] += 1
                table, store = (wanted_rgb, colour) if conn.topic == rgb_t else (wanted_depth, depth)
                if index not in table:
                    continue
                msg = reader.deserialize(raw, conn.msgtype)
                image = _colour(msg, conn.msgtype, rgb_t) if conn.topic == rgb_t else _depth_m(msg, depth_t)
                if image.shape[:2] != (camera.height, camera.width):
                    raise RosbagError(f"{conn.topic}: image {image.shape[1]}x{image.shape[0]}, CameraInfo on {info_t} "
                                      f"says {camera.width}x{camera.height}")
                store[table[index]] = image
                while written in colour and written in depth:
                    bgr, d = colour.pop(written), depth.pop(written)
                    if maps is not None:
                        bgr = cv2.remap(bgr, *maps, cv2.INTER_LINEAR)
                        d = cv2.remap(d, *maps, cv2.INTER_NEAREST)
                    writer.add_frame(rgb_times[use[written]], cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), d)
                    written += 1
                    if progress is not None:
                        progress(written, len(use))
            writer.set_odometry(odometry)
            writer.set_orthophoto(aerial)
            writer.set_meta({"source": f"ROS bag {', '.join(b.name for b in bags)}",
                             "topics": {"rgb": rgb_t, "depth": depth_t, "camera_info": info_t, "odometry": odom_t},
                             "camera_at_base": at_base})
    return {"frames": written, "unpaired": int((pair < 0).sum()), "without_pose": int(((pair >= 0) & ~covered).sum())}
