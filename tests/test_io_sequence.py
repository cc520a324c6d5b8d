"""Sequence folders: writer/reader round trip, one test per bad-input class, atomic writes."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.atomic import atomic_directory, atomic_path, write_text_atomic
from meridian_torch.io.camera import CameraModel
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.io.sequence import SequenceReader, SequenceWriter, check_sequence, read_camera

W, H = 32, 24
FRAME_TIMES = np.array([10.0, 10.1, 10.2, 10.3])


def make_camera() -> CameraModel:
    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # optical z forward = base x
    T[:3, 3] = [0.2, 0.0, 1.1]
    return CameraModel(W, H, 30.0, 31.0, 15.5, 11.5, 1000.0, T)


def circle(t: np.ndarray) -> np.ndarray:
    """T_odom_base of a car on a circle of radius 10 m at 2 m/s (constant body twist)."""
    yaw = 0.2 * np.asarray(t)
    T = np.tile(np.eye(4), (len(yaw), 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    T[:, 0, 3], T[:, 1, 3] = 10.0 * np.sin(yaw), 10.0 * (1.0 - np.cos(yaw))
    return T


def make_frames(seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    frames = []
    for _ in FRAME_TIMES:
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        depth = rng.uniform(0.1, 60.0, (H, W)).astype(np.float32)
        depth[0, :4] = [0.0, np.nan, np.inf, 70.0]  # none, invalid, invalid, beyond 65.535 m
        frames.append((rgb, depth))
    return frames


def write_sequence(path: Path, **writer_kwargs: object) -> list[tuple[np.ndarray, np.ndarray]]:
    frames = make_frames()
    odom_t = np.arange(9.5, 10.51, 0.5)  # 2 Hz odometry, 10 Hz frames
    aerial = np.random.default_rng(1).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    ortho = Orthophoto(aerial, 0.25, (100.0, 200.0))
    with SequenceWriter(path, make_camera(), **writer_kwargs) as writer:
        for t, (rgb, depth) in zip(FRAME_TIMES, frames):
            writer.add_frame(t, rgb, depth)
        writer.set_odometry(Trajectory(odom_t, circle(odom_t)))
        writer.set_groundtruth(Trajectory(FRAME_TIMES, circle(FRAME_TIMES)))
        writer.set_orthophoto(ortho)
        writer.set_meta({"name": "synthetic", "source": "test", "notes": ""})
        (writer.extra_dir / "sim").mkdir()
        (writer.extra_dir / "sim" / "world.json").write_text("{}")
    return frames


@pytest.fixture
def seq(tmp_path: Path) -> Path:
    write_sequence(tmp_path / "seq")
    return tmp_path / "seq"


def test_round_trip(tmp_path: Path) -> None:
    frames = write_sequence(tmp_path / "seq")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # no temporary siblings left
    assert check_sequence(tmp_path / "seq") == []
    reader = SequenceReader(tmp_path / "seq")
    camera = make_camera()
    assert reader.camera.width == W and reader.camera.height == H
    cam = reader.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (30.0, 31.0, 15.5, 11.5, 1000.0)
    np.testing.assert_array_equal(reader.camera.T_base_camera, camera.T_base_camera)
    assert len(reader) == 4
    np.testing.assert_array_equal(reader.frame_times, FRAME_TIMES)
    assert reader.meta == {"name": "synthetic", "source": "test", "notes": ""}
    assert reader.groundtruth is not None
    np.testing.assert_allclose(reader.groundtruth.poses, circle(FRAME_TIMES), atol=1e-12)
    assert (tmp_path / "seq/sim/world.json").is_file()
    ortho = reader.ortho()
    assert ortho.meters_per_pixel == 0.25 and ortho.origin_xy == (100.0, 200.0)
    assert ortho.image.shape == (20, 30, 3)
    for frame, (rgb, depth) in zip(reader, frames, strict=True):
        np.testing.assert_array_equal(frame.rgb, rgb)
        assert frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
        np.testing.assert_array_equal(frame.depth[0, :4], 0.0)  # zero, NaN, inf, too far -> no depth
        np.testing.assert_allclose(frame.depth[:, 4:], depth[:, 4:], atol=1.0 / camera.depth_scale)
        # Odometry at 2 Hz interpolated at 10 Hz frame times: exact for constant twist.
        np.testing.assert_allclose(frame.T_odom_base, circle(np.array([frame.timestamp]))[0], atol=1e-9)
    assert reader[-1].index == 3
    with pytest.raises(IndexError):
        reader[4]


def test_images_are_loaded_lazily(seq: Path) -> None:
    (seq / "ground/rgb/000003.png").unlink()
    reader = SequenceReader(seq)  # does not touch images
    assert reader[0].index == 0
    with pytest.raises(SequenceFormatError, match="000003.png: file not found"):
        reader[3]


# ------------------------------------------------------------------ one test per bad-input class


def _edit(path: Path, fn: Callable[[str], str]) -> None:
    path.write_text(fn(path.read_text()))


def _edit_tum_line(path: Path, line: int, fn: Callable[[list[str]], list[str]]) -> None:
    """Apply `fn` to the fields of the `line`-th data line (0-based) of a TUM file."""
    lines = path.read_text().splitlines()
    data = [i for i, s in enumerate(lines) if s and not s.startswith("#")]
    lines[data[line]] = " ".join(fn(lines[data[line]].split()))
    path.write_text("\n".join(lines) + "\n")


def _drop_camera_key(seq: Path) -> None:
    data = json.loads((seq / "ground/camera.json").read_text())
    del data["fx"]
    (seq / "ground/camera.json").write_text(json.dumps(data))


def _swap_frame_times(seq: Path) -> None:
    _edit(seq / "ground/frames.csv", lambda s: s.replace("10.100000000,", "10.250000000,"))


def _scale_quaternion(fields: list[str]) -> list[str]:
    return fields[:4] + [repr(float(v) * 1.1) for v in fields[4:]]


BAD_INPUTS: dict[str, tuple[Callable[[Path], None], str, int | str | None, str]] = {
    # name: (corrupt the sequence, offending file, what fails: a frame index, "ortho" (read lazily)
    # or None (opening the sequence), part of the message)
    "missing_file": (lambda s: (s / "ground/odometry.tum").unlink(), "odometry.tum", None, "file not found"),
    "missing_image": (lambda s: (s / "ground/depth/000002.png").unlink(), "000002.png", 2, "file not found"),
    "missing_key": (_drop_camera_key, "camera.json", None, "missing key 'fx'"),
    "image_size": (
        lambda s: cv2.imwrite(str(s / "ground/rgb/000001.png"), np.zeros((H, W - 1, 3), np.uint8)),
        "000001.png", 1, f"is {W - 1}x{H} but camera.json says {W}x{H}",
    ),
    "depth_8bit": (
        lambda s: cv2.imwrite(str(s / "ground/depth/000001.png"), np.zeros((H, W), np.uint8)),
        "000001.png", 1, "8-bit depth",
    ),
    "nan_in_tum": (
        lambda s: _edit_tum_line(s / "ground/odometry.tum", 1, lambda f: f[:2] + ["nan"] + f[3:]),
        "odometry.tum", None, "line 4: NaN or infinite",
    ),
    "inf_in_groundtruth": (
        lambda s: _edit_tum_line(s / "groundtruth.tum", 0, lambda f: f[:3] + ["-inf"] + f[4:]),
        "groundtruth.tum", None, "NaN or infinite",
    ),
    "frames_not_increasing": (
        _swap_frame_times, "frames.csv", None, "line 4: timestamp 10.200000000 not greater"
    ),
    "tum_not_increasing": (
        lambda s: _edit_tum_line(s / "ground/odometry.tum", 1, lambda f: ["9.4"] + f[1:]),
        "odometry.tum", None, "line 4: timestamp 9.400000000 not greater",
    ),
    "odometry_not_covering": (
        lambda s: _edit_tum_line(s / "ground/odometry.tum", 2, lambda f: ["#"] + f),
        "odometry.tum", None, "must cover them all",
    ),
    "non_unit_quaternion": (
        lambda s: _edit_tum_line(s / "ground/odometry.tum", 0, _scale_quaternion),
        "odometry.tum", None, "quaternion norm 1.1",
    ),
    "bad_ortho_json": (
        lambda s: _edit(s / "aerial/ortho.json", lambda t: t.replace("0.25", "-0.25")),
        "ortho.json", "ortho", "key 'meters_per_pixel' must be",
    ),
    "missing_aerial_image": (
        lambda s: (s / "aerial/ortho.png").unlink(), "aerial", None, "no orthophoto found"
    ),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input(seq: Path, case: str) -> None:
    corrupt, filename, frame, message = BAD_INPUTS[case]
    corrupt(seq)
    with pytest.raises(SequenceFormatError) as info:
        reader = SequenceReader(seq)
        if frame == "ortho":
            reader.ortho()
        elif frame is not None:
            reader[frame]
    assert filename in str(info.value) and message in str(info.value)
    problems = check_sequence(seq)
    assert any(filename in p and message in p for p in problems), problems


def test_check_sequence_reports_every_problem(seq: Path) -> None:
    for case in ("missing_image", "image_size", "nan_in_tum", "frames_not_increasing", "bad_ortho_json"):
        BAD_INPUTS[case][0](seq)
    problems = check_sequence(seq)
    for part in ("000002.png", "000001.png", "NaN or infinite", "not greater", "ortho.json"):
        assert any(part in p for p in problems), (part, problems)


def test_read_camera_rejects_bad_values(tmp_path: Path) -> None:
    cam = {"width": 0, "height": 2.5, "fx": float("nan"), "fy": 1, "cx": 0, "cy": 0, "depth_scale": 1000,
           "T_base_camera": (2 * np.eye(4)).tolist(), "k1": 0}
    (tmp_path / "camera.json").write_text(json.dumps(cam))
    with pytest.raises(SequenceFormatError, match="camera.json: unknown key 'k1'"):
        read_camera(tmp_path / "camera.json")
    del cam["k1"]
    for key, bad in (("width", 0), ("height", 2.5), ("fx", float("nan")), ("T_base_camera", None)):
        cam_ok = {**cam, "width": 4, "height": 3, "fx": 1.0, "T_base_camera": np.eye(4).tolist(), key: bad}
        (tmp_path / "camera.json").write_text(json.dumps(cam_ok))
        with pytest.raises(SequenceFormatError, match=f"camera.json: key '{key}' must be"):
            read_camera(tmp_path / "camera.json")
    (tmp_path / "camera.json").write_text(json.dumps({**cam, "width": 4, "height": 3, "fx": 1.0}))
    with pytest.raises(SequenceFormatError, match="not a rigid transform"):
        read_camera(tmp_path / "camera.json")


# ------------------------------------------------------------------ writer atomicity


def test_writer_leaves_nothing_on_error(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="boom"):
        with SequenceWriter(tmp_path / "seq", make_camera()) as writer:
            writer.add_frame(0.0, np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("missing", ["odometry", "orthophoto", "frames", "coverage"])
def test_writer_close_fails_clearly(tmp_path: Path, missing: str) -> None:
    writer = SequenceWriter(tmp_path / "seq", make_camera())
    if missing != "frames":
        writer.add_frame(1.0, np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32))
    if missing != "odometry":
        t = np.array([0.0, 0.5]) if missing == "coverage" else np.array([0.0, 2.0])
        writer.set_odometry(Trajectory(t, np.tile(np.eye(4), (2, 1, 1))))
    if missing != "orthophoto":
        writer.set_orthophoto(Orthophoto(np.zeros((4, 4, 3), np.uint8), 1.0, (0.0, 0.0)))
    expected = {"odometry": "odometry missing", "orthophoto": "orthophoto missing",
                "frames": "no frames", "coverage": "must cover"}[missing]
    with pytest.raises(SequenceFormatError, match=expected):
        writer.close()
    assert list(tmp_path.iterdir()) == []


def test_writer_rejects_non_increasing_timestamps(tmp_path: Path) -> None:
    with pytest.raises(SequenceFormatError, match="not greater"):
        with SequenceWriter(tmp_path / "seq", make_camera()) as writer:
            for t in (1.0, 1.0):
                writer.add_frame(t, np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32))
    assert list(tmp_path.iterdir()) == []


def test_writer_overwrite(seq: Path) -> None:
    with pytest.raises(SequenceFormatError, match="already exists"):
        SequenceWriter(seq, make_camera())
    (seq / "stale.txt").write_text("old")
    write_sequence(seq, overwrite=True)
    assert not (seq / "stale.txt").exists() and check_sequence(seq) == []
    assert sorted(p.name for p in seq.parent.iterdir()) == ["seq"]


def test_atomic_path_keeps_old_content_on_error(tmp_path: Path) -> None:
    target = tmp_path / "a.txt"
    write_text_atomic(target, "old")
    with pytest.raises(ValueError):
        with atomic_path(target) as tmp:
            assert tmp.suffix == ".txt" and tmp.parent == tmp_path
            tmp.write_text("half")
            raise ValueError
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_atomic_directory(tmp_path: Path) -> None:
    target = tmp_path / "out"
    with atomic_directory(target) as tmp:
        (tmp / "x").write_text("1")
        assert not target.exists()
    assert (target / "x").read_text() == "1"
    with pytest.raises(FileExistsError):
        with atomic_directory(target):
            pass
    with atomic_directory(target, overwrite=True) as tmp:
        (tmp / "y").write_text("2")
    assert sorted(p.name for p in target.iterdir()) == ["y"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_atomic_files_get_the_mode_of_a_plain_open(tmp_path: Path) -> None:
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    atomic = tmp_path / "atomic.txt"
    write_text_atomic(atomic, "x")
    assert atomic.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777


def _gaps_loop(odom_t: np.ndarray, query: np.ndarray, max_gap: float) -> list[tuple[float, float]]:
    gaps = set()
    for q in query:
        for a, b in zip(odom_t[:-1], odom_t[1:]):
            if a < q < b and b - a > max_gap:
                gaps.add((a, b))
    return sorted(gaps)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 200), min_size=1, max_size=25, unique=True),
       st.lists(st.integers(-10, 210), max_size=25), st.integers(1, 40))
def test_gaps_bridged_equals_a_slow_loop(odom: list[int], query: list[int], max_gap: int) -> None:
    odom_t = np.sort(np.array(odom, dtype=np.float64)) / 4.0
    traj = Trajectory(odom_t, np.tile(np.eye(4), (len(odom_t), 1, 1)))
    query_t = np.array(query, dtype=np.float64) / 4.0 + 0.125 * (np.arange(len(query)) % 2)
    got = [tuple(g) for g in traj.gaps_bridged(query_t, max_gap / 4.0)]
    assert got == _gaps_loop(odom_t, query_t, max_gap / 4.0)


def test_frames_inside_an_odometry_gap_are_refused_before_the_run(tmp_path: Path) -> None:
    """2 Hz odometry under frames at 10.0-10.3 s: fine at a 1 s limit, refused at 0.3 s (three frames lie
    strictly between the poses at 10.0 and 10.5 s), by the reader and by check."""
    write_sequence(tmp_path / "seq")
    reader = SequenceReader(tmp_path / "seq")
    reader.require_odometry_without_gaps(1.0)
    with pytest.raises(SequenceFormatError, match=r"odometry\.tum: no pose between 10\.0+ and 10\.50* s .* "
                                                  r"ground_map\.max_odometry_gap_s = 0\.3 s\) but 3 frame\(s\)"):
        reader.require_odometry_without_gaps(0.3)
    assert check_sequence(tmp_path / "seq") == []
    problems = check_sequence(tmp_path / "seq", max_odometry_gap_s=0.3)
    assert len(problems) == 1 and "odometry.tum: no pose between" in problems[0]


def test_localize_refuses_an_odometry_gap_before_mapping(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from meridian_torch.config import MeridianConfig
    from meridian_torch.mapping import ground_map
    from meridian_torch.pipeline import localize_sequence
    from meridian_torch.runtime import resolve_runtime

    write_sequence(tmp_path / "seq")
    cfg = MeridianConfig()
    cfg = cfg.model_copy(update={"ground_map": cfg.ground_map.model_copy(update={"max_odometry_gap_s": 0.3})})
    monkeypatch.setattr(ground_map.GroundMapper, "from_config", lambda *a, **k: pytest.fail("mapping started"))
    with pytest.raises(SequenceFormatError, match="no pose between"):
        localize_sequence(SequenceReader(tmp_path / "seq"), None, cfg, resolve_runtime(cfg.runtime))
    with pytest.raises(SequenceFormatError, match="no pose between"):
        ground_map.map_ground(SequenceReader(tmp_path / "seq"), cfg, resolve_runtime(cfg.runtime))


def test_check_decodes_every_image_unless_quick(seq: Path) -> None:
    """A truncated frame has a valid header: only decoding finds it, before a run reaches it."""
    from typer.testing import CliRunner

    from meridian_torch.cli import app

    png = seq / "ground" / "rgb" / "000002.png"
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    problems = check_sequence(seq)
    assert len(problems) == 1 and problems[0].startswith(f"{png}: image data cannot be decoded")
    assert check_sequence(seq, quick=True) == []
    result = CliRunner().invoke(app, ["check", str(seq)])
    assert result.exit_code == 1 and "000002.png: image data cannot be decoded" in result.output
    assert CliRunner().invoke(app, ["check", str(seq), "--quick"]).exit_code == 0
