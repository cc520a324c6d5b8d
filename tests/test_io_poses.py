"""TUM / KITTI pose files and odometry interpolation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from meridian_torch.errors import SequenceFormatError
from meridian_torch.geometry.se3 import se3_exp, so3_exp
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.poses import parse_tum, read_kitti, read_tum, write_kitti, write_tum


def random_trajectory(n: int, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    times = 1.7e9 + np.cumsum(rng.uniform(1e-3, 2.0, n))  # unix-like times: the hard case for %.9f
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = so3_exp(rng.normal(size=(n, 3)) * 2.0)
    poses[:, :3, 3] = rng.normal(size=(n, 3)) * 1e3
    return Trajectory(times, poses)


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_tum_round_trip(tmp_path_factory: pytest.TempPathFactory, n: int, seed: int) -> None:
    traj = random_trajectory(n, seed)
    path = tmp_path_factory.mktemp("tum") / "traj.tum"
    write_tum(path, traj, comment="T_odom_base\nsecond line")
    back = read_tum(path)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, rtol=0, atol=5e-10)
    np.testing.assert_allclose(back.poses, traj.poses, rtol=0, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_kitti_round_trip(tmp_path_factory: pytest.TempPathFactory, n: int, seed: int) -> None:
    traj = random_trajectory(n, seed)
    folder = tmp_path_factory.mktemp("kitti")
    write_kitti(folder / "poses.txt", traj, times_path=folder / "times.txt")
    back = read_kitti(folder / "poses.txt", folder / "times.txt")
    np.testing.assert_allclose(back.timestamps, traj.timestamps, rtol=0, atol=5e-10)
    np.testing.assert_allclose(back.poses, traj.poses, rtol=0, atol=1e-12)
    given_times = read_kitti(folder / "poses.txt", timestamps=traj.timestamps)
    np.testing.assert_array_equal(given_times.timestamps, traj.timestamps)


def test_kitti_default_timestamps_are_10hz(tmp_path: Path) -> None:
    write_kitti(tmp_path / "poses.txt", random_trajectory(5, 0))
    np.testing.assert_allclose(read_kitti(tmp_path / "poses.txt").timestamps, np.arange(5) * 0.1)


def test_comments_blank_lines_and_small_quaternion_error(tmp_path: Path) -> None:
    q = np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)]) * (1 + 5e-4)  # renormalised, not an error
    path = tmp_path / "t.tum"
    quat = " ".join(map(str, q))
    path.write_text(f"# header\n\n1.0 1 2 3 {quat}\n  # indented comment\n2.0 0 0 0 0 0 0 1\n")
    traj = read_tum(path)
    assert len(traj) == 2
    np.testing.assert_allclose(traj.poses[0, :3, :3], so3_exp(np.array([0, 0, 0.6])), atol=1e-12)


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n", "line 2: expected 8 columns"),
        ("1 0 0 0 0 0 0 1\n2 0 x 0 0 0 0 1\n", "line 2: not a number: 'x'"),
        ("1 0 0 0 0 0 0 1\n2 0 nan 0 0 0 0 1\n", "line 2: NaN or infinite"),
        ("1 0 0 0 0 0 0 1\n2 inf 0 0 0 0 0 1\n", "line 2: NaN or infinite"),
        ("# c\n1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "line 3: timestamp 1.000000000 not greater"),
        ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1.01\n", "line 2: quaternion norm 1.01"),
        ("1 0 0 0 0 0 0 0\n", "line 1: quaternion norm 0"),
        ("# only a comment\n\n", "empty file"),
        ("", "empty file"),
    ],
)
def test_tum_errors_name_file_and_line(tmp_path: Path, content: str, expected: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(content)
    with pytest.raises(SequenceFormatError, match="bad.tum") as info:
        read_tum(path)
    assert expected in str(info.value)


def test_tum_missing_file(tmp_path: Path) -> None:
    with pytest.raises(SequenceFormatError, match="nope.tum: file not found"):
        read_tum(tmp_path / "nope.tum")


def test_parse_tum_collects_all_problems(tmp_path: Path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 2\n3 nan 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n")
    traj, problems = parse_tum(path)
    assert traj is None
    assert [p.split(": ")[1] for p in problems] == ["line 3", "line 2", "line 4"]


def test_kitti_rotation_checks(tmp_path: Path) -> None:
    R = so3_exp(np.array([0.1, -0.2, 0.3]))
    good = np.hstack([R + 2e-4, np.ones((3, 1))])  # off by < 1e-3: re-orthonormalised
    bad = np.hstack([R * 1.01, np.ones((3, 1))])
    reflection = np.hstack([-R, np.ones((3, 1))])
    path = tmp_path / "poses.txt"
    path.write_text(" ".join(repr(float(v)) for v in good.ravel()) + "\n")
    T = read_kitti(path).poses[0]
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-3)
    for matrix in (bad, reflection):
        path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" + " ".join(repr(float(v)) for v in matrix.ravel()) + "\n")
        with pytest.raises(SequenceFormatError, match=r"poses.txt: line 2: rotation is not orthonormal"):
            read_kitti(path)


def test_kitti_times_mismatch(tmp_path: Path) -> None:
    write_kitti(tmp_path / "poses.txt", random_trajectory(3, 1))
    (tmp_path / "times.txt").write_text("0\n1\n")
    with pytest.raises(SequenceFormatError, match="times.txt: 2 timestamps but"):
        read_kitti(tmp_path / "poses.txt", tmp_path / "times.txt")
    (tmp_path / "times.txt").write_text("0\n1\n1\n")
    with pytest.raises(SequenceFormatError, match="times.txt: line 3: timestamp"):
        read_kitti(tmp_path / "poses.txt", tmp_path / "times.txt")


# ---------------------------------------------------------------- interpolation vs analytic motion


def helix_pose(t: np.ndarray, v: float, vz: float, omega: float, yaw0: float) -> np.ndarray:
    """Closed form of constant body twist (forward v, climb vz, yaw rate omega) from the origin."""
    t = np.asarray(t, dtype=np.float64)
    yaw = yaw0 + omega * t
    T = np.tile(np.eye(4), t.shape + (1, 1))
    T[..., 0, 0], T[..., 0, 1] = np.cos(yaw), -np.sin(yaw)
    T[..., 1, 0], T[..., 1, 1] = np.sin(yaw), np.cos(yaw)
    r = v / omega
    T[..., 0, 3] = r * (np.sin(yaw) - math.sin(yaw0))
    T[..., 1, 3] = -r * (np.cos(yaw) - math.cos(yaw0))
    T[..., 2, 3] = vz * t
    return T


@pytest.mark.parametrize(
    ("vz", "omega", "yaw0", "dt"),
    [
        (0.0, 0.3, 0.0, 0.5),  # car on a circle, 10 Hz frames, 2 Hz odometry
        (0.4, -0.7, 0.2, 1.0),  # helix turning right
        (0.1, 1.1, 2.9, 2.0),  # crosses yaw = +pi with 2.2 rad between samples
        (0.0, -2.0, -3.0, 0.7),  # crosses yaw = -pi
    ],
)
def test_interpolation_matches_analytic_motion(vz: float, omega: float, yaw0: float, dt: float) -> None:
    sample_t = np.arange(0.0, 12.0 + 1e-9, dt) + 100.0
    traj = Trajectory(sample_t, helix_pose(sample_t - 100.0, 5.0, vz, omega, yaw0))
    query = np.linspace(sample_t[0], sample_t[-1], 97)
    expected = helix_pose(query - 100.0, 5.0, vz, omega, yaw0)
    np.testing.assert_allclose(traj.interpolate(query), expected, rtol=0, atol=1e-9)
    assert np.any(np.abs(np.diff(traj.yaws)) > np.pi)  # every case wraps past +-pi


def test_interpolation_through_tum_file_matches_analytic(tmp_path: Path) -> None:
    sample_t = np.arange(0.0, 20.0 + 1e-9, 0.5)
    write_tum(tmp_path / "odometry.tum", Trajectory(sample_t, helix_pose(sample_t, 8.0, 0.2, 0.9, 3.0)))
    query = np.linspace(0.0, 20.0, 201)
    np.testing.assert_allclose(
        read_tum(tmp_path / "odometry.tum").interpolate(query),
        helix_pose(query, 8.0, 0.2, 0.9, 3.0),
        rtol=0,
        atol=1e-9,
    )


@settings(max_examples=50, deadline=None)
@given(
    xi=st.lists(st.floats(-2.0, 2.0), min_size=6, max_size=6),
    s=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_interpolation_is_constant_twist_geodesic(xi: list[float], s: float, seed: int) -> None:
    # xi is (v, omega): the geodesic is the shortest rotation, so the twist's
    # rotation angle must stay below pi (else exp(s * xi) is the long way round).
    assume(np.linalg.norm(xi[3:]) < np.pi - 1e-3)
    T0 = random_trajectory(1, seed).poses[0]
    twist = np.array(xi)
    T1 = T0 @ se3_exp(twist)
    traj = Trajectory(np.array([10.0, 12.0]), np.stack([T0, T1]))
    got = traj.interpolate(np.array([10.0, 10.0 + 2.0 * s, 12.0]))
    np.testing.assert_allclose(got[0], T0, atol=1e-9)
    np.testing.assert_allclose(got[2], T1, atol=1e-6)  # 1e3 m translations: relative 1e-9
    np.testing.assert_allclose(got[1], T0 @ se3_exp(twist * s), atol=1e-6)
