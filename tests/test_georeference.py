"""Absolute coordinates and times: a projected CRS's coordinates (UTM: ~5e5 m east, ~5e6 m north)
and Unix timestamps (~1.7e9 s) give the same map and the same trajectory as small ones.

The aerial map works in a map frame around a local origin (`map_frame_origin`) and the localizer
returns world coordinates in float64; these tests shift inputs by such offsets and compare.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.backend.localizer import Localizer
from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.io.ortho import Orthophoto
from meridian_torch.mapping.aerial_map import AerialMapper, build_aerial_map, map_frame_origin
from meridian_torch.sim.simulate import simulate_sequence

UTM_OFFSET = (500_000.0, 5_400_000.0)
UNIX_TIME = 1.7e9


def _world_primitives(aerial_map) -> tuple[np.ndarray, np.ndarray]:
    """Valid points (N, 2) and line endpoints (L, 2, 2) of a map in world coordinates (float64)."""
    p = aerial_map.primitives
    origin = np.asarray(aerial_map.local_origin_xy)
    points = p.points_xy[p.point_valid].double().numpy() + origin
    lines = p.line_endpoints[p.line_valid].double().numpy() + origin
    return points, lines


@settings(max_examples=200, deadline=None)
@given(st.floats(-2e7, 2e7), st.floats(-2e7, 2e7))
def test_the_map_frame_keeps_coordinates_small_and_round(x: float, y: float) -> None:
    ortho = Orthophoto(np.zeros((1, 1, 3), np.uint8), 0.3, (x, y))
    local = map_frame_origin(ortho)
    assert all(v % 10_000.0 == 0.0 for v in local)
    assert abs(x - local[0]) <= 5_000.0 and abs(y - local[1]) <= 5_000.0
    if abs(x) < 5_000.0 and abs(y) < 5_000.0:
        assert local == (0.0, 0.0)  # small worlds keep world coordinates


@pytest.fixture(scope="module")
def tiny_ortho(tmp_path_factory: pytest.TempPathFactory):
    cfg = load_config(CONFIG_DIR / "tiny.yaml")
    out = tmp_path_factory.mktemp("geo") / "tiny"
    simulate_sequence(cfg.sim, out)
    from meridian_torch.io.ortho import read_orthophoto

    mapper = AerialMapper.from_config(cfg.aerial_map, cfg.perception, cfg.primitives)
    ortho = read_orthophoto(out)
    return ortho, mapper, build_aerial_map(ortho, mapper)


@settings(max_examples=4, deadline=None)
@given(st.integers(-1000, 1000), st.integers(0, 1000))
def test_a_shifted_orthophoto_gives_the_same_map(tiny_ortho, kx: int, ky: int) -> None:
    """Shifts by whole 10 km steps (UTM-sized at the extremes) leave the map frame's content
    bitwise unchanged; the map's lattices (grid downsampling) are anchored in the map frame."""
    ortho, mapper, reference = tiny_ortho
    dx, dy = 10_000.0 * kx, 10_000.0 * ky
    shifted = dataclasses.replace(ortho, origin_xy=(ortho.origin_xy[0] + dx, ortho.origin_xy[1] + dy))
    aerial_map = build_aerial_map(shifted, mapper)
    assert aerial_map.local_origin_xy == (reference.local_origin_xy[0] + dx, reference.local_origin_xy[1] + dy)
    for name, value in vars(reference.primitives).items():
        assert torch.equal(getattr(aerial_map.primitives, name), value), name
    assert np.array_equal(aerial_map.patches.bounds_xy, reference.patches.bounds_xy)
    points, lines = _world_primitives(aerial_map)
    ref_points, ref_lines = _world_primitives(reference)
    np.testing.assert_allclose(points - (dx, dy), ref_points, atol=1e-6, rtol=0)
    np.testing.assert_allclose(lines - (dx, dy), ref_lines, atol=1e-6, rtol=0)


def test_the_localizer_returns_the_same_trajectory_in_utm_coordinates_and_unix_time() -> None:
    from test_backend_end_to_end import _config, make_world

    aerial, gt, odometry, submaps = make_world(n_frames=140, spacing_m=16.0)
    reference = Localizer(aerial, _config("particles"), odometry, gt.timestamps, seed=0)
    for s in submaps:
        reference.add_submap(s)
    expected = reference.finalize()
    assert expected.localized

    # The same map with its frame at a UTM-sized local origin; every time shifted to Unix time.
    utm_map = dataclasses.replace(
        aerial, origin_xy=(aerial.origin_xy[0] + UTM_OFFSET[0], aerial.origin_xy[1] + UTM_OFFSET[1]),
        local_origin_xy=UTM_OFFSET,
    )
    utm_odometry = Trajectory(odometry.timestamps + UNIX_TIME, odometry.poses)
    utm_submaps = [dataclasses.replace(s, time=s.time + UNIX_TIME) for s in submaps]
    loc = Localizer(utm_map, _config("particles"), utm_odometry, gt.timestamps + UNIX_TIME, seed=0)
    for s in utm_submaps:
        loc.add_submap(s)
    result = loc.finalize()

    assert result.localized and result.fix_submap_index == expected.fix_submap_index
    for got, want in ((result.T_world_base, expected.T_world_base),
                      (result.T_world_base_incremental, expected.T_world_base_incremental)):
        assert np.array_equal(np.isnan(got), np.isnan(want))
        ok = np.isfinite(want[:, 0, 0])
        np.testing.assert_allclose(got[ok, :2, 3] - UTM_OFFSET, want[ok, :2, 3], atol=1e-3, rtol=0)
        np.testing.assert_allclose(got[ok, :3, :3], want[ok, :3, :3], atol=1e-9, rtol=0)
    np.testing.assert_allclose(
        result.inliers.T_world_base[:, :2, 2].numpy() - UTM_OFFSET, expected.inliers.T_world_base[:, :2, 2].numpy(),
        atol=1e-3, rtol=0,
    )


def shift_sequence(src: Path, dst: Path, dxy: tuple[float, float], dt: float, crs: str) -> None:
    """Copy a sequence folder with its world coordinates moved by `dxy` and every time by `dt`."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.mtm", "*.parts"))
    ortho_json = dst / "aerial" / "ortho.json"
    georef = json.loads(ortho_json.read_text())
    georef.update(origin=[georef["origin"][0] + dxy[0], georef["origin"][1] + dxy[1]], crs=crs)
    ortho_json.write_text(json.dumps(georef))
    for name, move in (("groundtruth.tum", True), ("ground/odometry.tum", False)):
        rows = []
        for line in (dst / name).read_text().splitlines():
            if line.startswith("#") or not line.strip():
                rows.append(line)
                continue
            v = line.split()
            v[0] = f"{float(v[0]) + dt:.9f}"
            if move:
                v[1], v[2] = repr(float(v[1]) + dxy[0]), repr(float(v[2]) + dxy[1])
            rows.append(" ".join(v))
        (dst / name).write_text("\n".join(rows) + "\n")
    header, *frames = (dst / "ground" / "frames.csv").read_text().splitlines()
    frames = [f"{float(r.split(',', 1)[0]) + dt:.9f},{r.split(',', 1)[1]}" for r in frames]
    (dst / "ground" / "frames.csv").write_text("\n".join([header, *frames]) + "\n")


@pytest.mark.slow
def test_a_utm_georeferenced_sequence_localizes_end_to_end(tmp_path: Path) -> None:
    """simulate -> shift to UTM 32N and Unix time -> localize: same trajectory, right lat/lon."""
    from pyproj import Transformer
    from typer.testing import CliRunner

    from meridian_torch.cli import app

    config = CONFIG_DIR / "tiny.yaml"
    sets = ["--set", "sim.trajectory.length_m=400", "--set", "sim.world.size_m=[200.0,200.0]"]
    runner = CliRunner()
    assert runner.invoke(app, ["simulate", "-o", str(tmp_path / "local"), "-c", str(config), *sets]).exit_code == 0
    shift_sequence(tmp_path / "local", tmp_path / "utm", UTM_OFFSET, UNIX_TIME, "EPSG:32632")
    for name in ("local", "utm"):
        result = runner.invoke(app, ["localize", str(tmp_path / name), "-m", str(tmp_path / f"{name}.mtm"),
                                     "-o", str(tmp_path / f"run-{name}"), "-c", str(config), *sets])
        assert result.exit_code == 0, result.output
        assert "localized: yes" in result.output

    for name in ("trajectory.tum", "trajectory_incremental.tum"):
        # ndmin: a late online fix may leave a single localized frame in the incremental file.
        want = np.loadtxt(tmp_path / "run-local" / name, ndmin=2)
        got = np.loadtxt(tmp_path / "run-utm" / name, ndmin=2)
        assert got.shape == want.shape and len(want) > 0
        np.testing.assert_allclose(got[:, 0] - UNIX_TIME, want[:, 0], atol=1e-6, rtol=0)
        np.testing.assert_allclose(got[:, 1:3] - UTM_OFFSET, want[:, 1:3], atol=1e-3, rtol=0)
        np.testing.assert_allclose(got[:, 3:], want[:, 3:], atol=1e-6, rtol=0)

    # lat/lon outputs agree with pyproj's transformation of the trajectory to 1e-8 deg (~1 mm).
    tum = np.loadtxt(tmp_path / "run-utm" / "trajectory.tum")
    latlon = np.genfromtxt(tmp_path / "run-utm" / "trajectory_latlon.csv", delimiter=",", names=True)
    to_wgs84 = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True)
    lon, lat = to_wgs84.transform(tum[:, 1], tum[:, 2])
    np.testing.assert_allclose(latlon["timestamp"], tum[:, 0], atol=1e-6, rtol=0)
    np.testing.assert_allclose(latlon["latitude"], lat, atol=1e-8, rtol=0)
    np.testing.assert_allclose(latlon["longitude"], lon, atol=1e-8, rtol=0)
