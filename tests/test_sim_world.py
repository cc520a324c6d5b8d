"""Procedural worlds, class-raster ground truth and the orthophoto renderer."""

from __future__ import annotations

import numpy as np
import pytest

from meridian_torch.config.sim import OrthoRenderConfig, WorldConfig
from meridian_torch.sim.classes import SimClass
from meridian_torch.sim.ground_truth import ground_layer, load_ground_truth, save_ground_truth
from meridian_torch.sim.ortho_render import render_orthophoto
from meridian_torch.sim.procedural import generate_world
from meridian_torch.sim.world import World

SMALL = WorldConfig(size_m=(120.0, 120.0), road_spacing_m=50.0, urban_fraction=0.6)


@pytest.fixture(scope="module")
def world() -> World:
    return generate_world(SMALL, seed=3)


def test_same_seed_same_world_other_seed_other_world(world: World) -> None:
    again = generate_world(SMALL, seed=3)
    for name in ("class_map", "height", "albedo", "wall_albedo", "instance_map"):
        np.testing.assert_array_equal(getattr(world, name), getattr(again, name))
    other = generate_world(SMALL, seed=4)
    assert not np.array_equal(world.class_map, other.class_map)


def test_objects_have_heights_and_instances(world: World) -> None:
    _, ground = ground_layer(world)
    for cls, min_h in ((SimClass.BUILDING, 4.0), (SimClass.TREE, 5.0)):
        objs = [o for o in world.objects if o.class_id == cls]
        assert objs, f"no {cls.name.lower()} in the world"
        for o in objs:
            cells = world.instance_map == o.object_id
            assert cells.any()
            assert np.all(world.class_map[cells] == cls)
            assert o.height_m >= min_h
            # A canopy may be partly hidden under a taller neighbour, never flat on the ground.
            assert (world.height[cells] - ground[cells]).max() >= 0.5 * min_h
    assert world.road_centrelines and (world.class_map == SimClass.ROAD).mean() > 0.05


def test_borders_lie_on_class_changes(world: World) -> None:
    assert len(world.borders) > 10
    regions, _ = ground_layer(world)
    regions[world.class_map == SimClass.BUILDING] = SimClass.BUILDING
    pts = np.concatenate([b.polyline_xy for b in world.borders])
    cr = np.round(world.world_to_cell(pts)).astype(int)
    h, w = world.shape
    changes = []
    for c, r in cr:
        win = regions[max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3]
        changes.append(len(np.unique(win)) > 1)
    assert np.mean(changes) > 0.97
    for b in world.borders:
        assert b.class_a < b.class_b
        assert np.linalg.norm(np.diff(b.polyline_xy, axis=0), axis=1).sum() >= 2.0


def test_ground_truth_round_trip(world: World, tmp_path) -> None:
    save_ground_truth(world, tmp_path / "gt")
    gt = load_ground_truth(tmp_path / "gt")
    np.testing.assert_array_equal(gt.class_map, world.class_map)
    np.testing.assert_allclose(gt.height, world.height, atol=0.02)
    assert gt.origin_xy == world.origin_xy and gt.resolution_m == world.resolution_m
    assert len(gt.objects) == len(world.objects) and len(gt.borders) == len(world.borders)
    np.testing.assert_allclose(gt.objects[0].footprint_xy, world.objects[0].footprint_xy, atol=1e-3)
    assert sorted(p.name for p in (tmp_path / "gt").iterdir()) == [
        "borders.json", "class_map.png", "height.npy", "objects.json", "world.json"]


def _tower_world() -> World:
    """60 x 60 m of flat grass with one 15 m tall, 10 x 10 m building in the middle."""
    n, res = 300, 0.2
    cls = np.full((n, n), SimClass.GRASS, np.uint8)
    height = np.zeros((n, n), np.float32)
    inst = np.full((n, n), -1, np.int32)
    sl = np.s_[125:175, 125:175]
    cls[sl], height[sl], inst[sl] = SimClass.BUILDING, 15.0, 0
    albedo = np.full((n, n, 3), 0.4, np.float32)
    return World(res, (0.0, 60.0), cls, height, albedo, albedo.copy(), inst)


def test_shadow_falls_away_from_the_sun() -> None:
    world = _tower_world()
    cfg = OrthoRenderConfig(meters_per_pixel=0.2, sun_azimuth_deg=135.0, sun_elevation_deg=45.0, texture_strength=0.0)
    img = render_orthophoto(world, cfg, seed=0).image.mean(axis=2)
    # Sun from the south-east: the shadow lies north-west (up-left), 15 m long.
    north_west = img[100:120, 100:120].mean()
    south_east = img[180:200, 180:200].mean()
    assert north_west < 0.75 * south_east
    flat = render_orthophoto(world, cfg.model_copy(update={"shadows": False}), seed=0).image.mean(axis=2)
    assert abs(flat[100:120, 100:120].mean() - south_east) < 5


def test_ortho_grid_and_outdated_changes_image_only(world: World) -> None:
    before = {k: getattr(world, k).copy() for k in ("class_map", "height", "albedo", "instance_map")}
    n_obj = len(world.objects)
    cfg = OrthoRenderConfig(meters_per_pixel=0.3)
    fresh = render_orthophoto(world, cfg, seed=1)
    old = render_orthophoto(world, cfg.model_copy(update={"outdated": True, "outdated_change_fraction": 0.3}), seed=1)
    assert fresh.origin_xy == world.origin_xy and fresh.image.shape == (400, 400, 3) and fresh.image.dtype == np.uint8
    diff = np.abs(fresh.image.astype(int) - old.image.astype(int)).mean(axis=2)
    assert (diff > 30).mean() > 0.005
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(world, k), v)
    assert len(world.objects) == n_obj
    np.testing.assert_array_equal(render_orthophoto(world, cfg, seed=1).image, fresh.image)
