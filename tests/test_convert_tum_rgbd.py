"""`meridian-torch convert tum-rgbd`: pairing by time, a round trip through the TUM layout, bad inputs."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from meridian_torch.cli import app
from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.converters.sync import T_BASE_OPTICAL, associate
from meridian_torch.io.converters.tum_rgbd import TUM_DEPTH_SCALE, TumRgbdError, convert_tum_rgbd
from meridian_torch.io.poses import write_tum
from meridian_torch.io.sequence import SequenceReader, check_sequence
from meridian_torch.sim.simulate import simulate_sequence

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "open3d_testdata_rgbd"


def _associate_loop(rgb: np.ndarray, depth: np.ndarray, max_dt: float) -> np.ndarray:
    """Nearest depth per colour image within max_dt; a depth image keeps only its closest colour image."""
    pair = []
    for t in rgb:
        j = int(np.argmin(np.abs(depth - t)))  # ties: the earlier depth image
        pair.append(j if abs(depth[j] - t) <= max_dt else -1)
    pair = np.array(pair)
    for j in set(pair[pair >= 0].tolist()):
        users = np.flatnonzero(pair == j)
        best = users[np.argmin(np.abs(rgb[users] - depth[j]))]
        pair[users[users != best]] = -1
    return pair


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 400), min_size=1, max_size=30, unique=True),
       st.lists(st.integers(0, 400), min_size=1, max_size=30, unique=True), st.integers(1, 30))
def test_association_equals_a_slow_loop(rgb: list[int], depth: list[int], max_dt: int) -> None:
    # Times on a 1/128 s grid plus distinct offsets: exact in float, no equidistant ties.
    rgb_t = np.sort(np.array(rgb) / 128.0 + 1e-5)
    depth_t = np.sort(np.array(depth) / 128.0)
    expected = _associate_loop(rgb_t, depth_t, max_dt / 128.0)
    np.testing.assert_array_equal(associate(rgb_t, depth_t, max_dt / 128.0), expected)


@pytest.fixture(scope="module")
def tum_tree(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny simulated sequence rewritten in the TUM RGB-D layout (depth a few ms after colour)."""
    root = tmp_path_factory.mktemp("tum")
    cfg = load_config(CONFIG_DIR / "tiny.yaml")
    simulate_sequence(cfg.sim, root / "seq")
    reader = SequenceReader(root / "seq")
    tum = root / "rgbd_dataset"
    (tum / "rgb").mkdir(parents=True)
    (tum / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for i in range(len(reader)):
        frame = reader[i]
        t = 1.3e9 + frame.timestamp
        cv2.imwrite(str(tum / "rgb" / f"{t:.6f}.png"), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
        units = np.rint(frame.depth * TUM_DEPTH_SCALE)
        units[units > 65535] = 0  # TUM's 16-bit depth ends at 13.1 m
        cv2.imwrite(str(tum / "depth" / f"{t + 0.004:.6f}.png"), units.astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    (tum / "rgb.txt").write_text("# colour images\n# file: 'rgbd_dataset'\n# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (tum / "depth.txt").write_text("# depth images\n" + "\n".join(depth_lines) + "\n")
    odom = reader.odometry
    T_odom_camera = odom.poses @ reader.camera.T_base_camera
    write_tum(tum / "groundtruth.txt", Trajectory(odom.timestamps + 1.3e9, T_odom_camera))
    return root / "seq", tum


def test_a_tum_tree_converts_back_to_the_same_frames_and_odometry(tum_tree, tmp_path: Path) -> None:
    seq, tum = tum_tree
    counts = convert_tum_rgbd(tum, seq / "aerial", tmp_path / "out", camera="fr3")
    assert check_sequence(tmp_path / "out") == []
    original, converted = SequenceReader(seq), SequenceReader(tmp_path / "out")
    assert counts == {"frames": len(original), "unpaired": 0, "without_pose": 0} and len(converted) == len(original)
    np.testing.assert_allclose(converted.frame_times, original.frame_times + 1.3e9, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(converted.camera.T_base_camera, T_BASE_OPTICAL)
    for i in (0, len(original) // 2, len(original) - 1):
        a, b = original[i], converted[i]
        np.testing.assert_array_equal(b.rgb, a.rgb)
        in_range = np.where(a.depth * TUM_DEPTH_SCALE <= 65535, a.depth, 0.0)
        np.testing.assert_allclose(b.depth, in_range, atol=0.5 / TUM_DEPTH_SCALE, rtol=0)
        # The same camera pose, whatever base frame each sequence uses.
        np.testing.assert_allclose(b.T_odom_base @ converted.camera.T_base_camera,
                                   a.T_odom_base @ original.camera.T_base_camera, atol=1e-6, rtol=0)


def test_distorted_cameras_are_undistorted_without_inventing_depth(tum_tree, tmp_path: Path) -> None:
    seq, tum = tum_tree
    convert_tum_rgbd(tum, seq / "aerial", tmp_path / "fr1", camera="fr1")
    original, converted = SequenceReader(seq)[3], SequenceReader(tmp_path / "fr1")[3]
    assert not np.array_equal(converted.rgb, original.rgb)
    measured = np.rint(original.depth * TUM_DEPTH_SCALE)
    invented = np.setdiff1d(np.rint(converted.depth * TUM_DEPTH_SCALE), np.append(measured, 0.0))
    assert len(invented) == 0  # nearest-neighbour remap: every depth value was measured


def test_cli_writes_a_sequence_and_refuses_to_overwrite(tum_tree, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    seq, tum = tum_tree
    runner = CliRunner()
    args = ["convert", "tum-rgbd", str(tum), "--ortho", str(seq / "aerial"), "--out", str(tmp_path / "o"),
            "--camera", "fr3"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "skipped 0 colour images" in result.output

    def must_not_read(*_args: object) -> None:
        raise AssertionError("the orthophoto was read before the existing output was refused")

    monkeypatch.setattr("meridian_torch.io.converters.tum_rgbd.read_orthophoto", must_not_read)
    again = runner.invoke(app, args)
    assert again.exit_code == 1 and "already exists" in again.output, again.output


@pytest.mark.parametrize("case", ["no depth list", "nothing within max dt", "missing image", "unknown camera"])
def test_bad_inputs_name_the_problem(tum_tree, tmp_path: Path, case: str) -> None:
    seq, tum = tum_tree
    broken = tmp_path / "tum"
    shutil.copytree(tum, broken)
    kwargs: dict = {"camera": "fr3"}
    if case == "no depth list":
        (broken / "depth.txt").unlink()
        match = "depth.txt: not found"
    elif case == "nothing within max dt":
        kwargs["max_dt_s"] = 0.001
        match = "no colour image has a depth image within 0.001 s"
    elif case == "missing image":
        next((broken / "rgb").iterdir()).unlink()
        match = r"rgb/.*\.png: missing or not a readable image"
    else:
        kwargs["camera"] = "kinect"
        match = "camera 'kinect'"
    with pytest.raises(TumRgbdError, match=match):
        convert_tum_rgbd(broken, seq / "aerial", tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()  # nothing half-written


def test_a_real_tum_frame_converts(tum_tree, tmp_path: Path) -> None:
    """The benchmark's own PNGs (Kinect colour, 16-bit depth at 5000 per metre) go through unchanged."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data/open3d_testdata_rgbd not present")
    seq, _ = tum_tree
    tum = tmp_path / "real"
    (tum / "rgb").mkdir(parents=True)
    (tum / "depth").mkdir()
    for k in range(2):  # the one real frame, twice, 1/30 s apart
        shutil.copy(SHARED / "RGBD/other_formats/TUM_color.png", tum / "rgb" / f"{k}.png")
        shutil.copy(SHARED / "RGBD/other_formats/TUM_depth.png", tum / "depth" / f"{k}.png")
    (tum / "rgb.txt").write_text("100.0 rgb/0.png\n100.033 rgb/1.png\n")
    (tum / "depth.txt").write_text("100.001 depth/0.png\n100.034 depth/1.png\n")
    (tum / "groundtruth.txt").write_text("99.9 0 0 1.2 0 0 0 1\n100.1 0.1 0 1.2 0 0 0 1\n")
    convert_tum_rgbd(tum, seq / "aerial", tmp_path / "out", camera="fr1")
    frame = SequenceReader(tmp_path / "out")[0]
    raw = cv2.imread(str(SHARED / "RGBD/other_formats/TUM_depth.png"), cv2.IMREAD_UNCHANGED)
    assert frame.rgb.shape == (480, 640, 3) and raw.dtype == np.uint16
    units = np.rint(frame.depth[frame.depth > 0].astype(np.float64) * TUM_DEPTH_SCALE)
    assert np.isin(units, raw[raw > 0]).all()  # every depth was measured (nearest-neighbour undistortion)
    assert 0.3 < np.median(frame.depth[frame.depth > 0]) < 6.0  # a room seen by a Kinect, in metres
