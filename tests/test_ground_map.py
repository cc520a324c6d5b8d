"""The ground mapping pipeline on the tiny simulated sequence, and the submap file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from meridian_torch.config import CONFIG_DIR, load_config
from meridian_torch.config.mapping import SubmapSpacingConfig
from meridian_torch.evaluation.primitive_metrics import line_metrics, world_ground_truth
from meridian_torch.geometry.se3 import se3_inverse
from meridian_torch.io.sequence import SequenceReader
from meridian_torch.io.submap_file import SubmapFileError, load_ground_submaps, save_ground_submaps
from meridian_torch.mapping.ground_map import GroundMapper, frames_to_map, map_ground
from meridian_torch.runtime import resolve_runtime
from meridian_torch.sim.ground_truth import load_ground_truth
from meridian_torch.sim.simulate import simulate_sequence

CFG = load_config(CONFIG_DIR / "tiny.yaml")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ground") / "seq"
    simulate_sequence(CFG.sim, out)
    return out


@pytest.fixture(scope="module")
def submaps(tiny: Path):
    calls = []
    result = map_ground(SequenceReader(tiny), CFG, resolve_runtime(CFG.runtime), progress=lambda d, n: calls.append((d, n)))
    assert calls[0] == (0, calls[-1][1]) and calls[-1][0] == calls[-1][1]
    return result


def _plain_loop(mapper: GroundMapper, reader: SequenceReader, indices) -> list:
    """The submaps of `mapper` fed the frames `indices` of `reader` by add_frames, a batch at a time."""
    out, size = [], mapper.cfg.batch_size
    for start in range(0, len(indices), size):
        out += mapper.add_frames([reader[int(i)] for i in indices[start : start + size]])
    return out + mapper.finish()


def _assert_same_submaps(these: list, those: list) -> None:
    """Bitwise the same submap times, poses and primitives."""
    assert len(these) == len(those)
    for a, b in zip(these, those):
        assert a.time == b.time and np.array_equal(a.T_odom_base, b.T_odom_base)
        for name in a.primitives.__dataclass_fields__:
            assert torch.equal(getattr(a.primitives, name), getattr(b.primitives, name)), name


def test_submaps_are_consistent_with_the_odometry(tiny: Path, submaps) -> None:
    reader = SequenceReader(tiny)
    assert len(submaps) >= 1
    assert [s.index for s in submaps] == list(range(len(submaps)))
    times = np.array([s.time for s in submaps])
    assert np.all(np.diff(times) >= 0)
    path = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(reader.T_odom_base[:, :3, 3], axis=0), axis=1))]
    for s in submaps:
        k = int(np.argmin(np.abs(reader.frame_times - s.time)))
        np.testing.assert_allclose(s.T_odom_base, reader.T_odom_base[k])
        assert s.path_length_m == pytest.approx(path[k])
        assert s.frame_descriptors.shape[0] >= 1
        assert torch.allclose(s.frame_descriptors.norm(dim=1), torch.ones(s.frame_descriptors.shape[0]), atol=1e-5)
        p = s.primitives
        assert p.points_xy.shape[0] + p.line_endpoints.shape[0] > 0
        # everything lies within the submap radius of the centre camera (odom x-y)
        centre = (s.T_odom_base @ reader.camera.T_base_camera)[:2, 3]
        xy = torch.cat([p.points_xy, p.line_endpoints.reshape(-1, 2)]).double().numpy()
        assert np.linalg.norm(xy - centre, axis=1).max() <= CFG.ground_map.submap_radius_m + 0.5


def _line_precision(reader, submaps, gt_lines, lateral_m=0.0, extra_yaw=0.0) -> tuple[float, float]:
    covered = total = 0.0
    for s in submaps:
        T_world_base = reader.groundtruth.interpolate(np.array([s.time]))[0]
        T_world_odom = T_world_base @ se3_inverse(s.T_odom_base)
        yaw = np.arctan2(T_world_odom[1, 0], T_world_odom[0, 0]) + extra_yaw
        R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        heading = np.arctan2(T_world_base[1, 0], T_world_base[0, 0])
        side = lateral_m * np.array([-np.sin(heading), np.cos(heading)])  # across the drive direction
        lines = s.primitives.line_endpoints.double().numpy() @ R.T + T_world_odom[:2, 3] + side
        m = line_metrics(lines, gt_lines, dist=1.0, angle_deg=10.0)
        covered += m["covered_pred_length"]
        total += m["pred_length"]
    return covered / max(total, 1e-9), total


def test_submap_lines_lie_on_true_borders(tiny: Path, submaps) -> None:
    # through the ground-truth pose, a good share of the line length lies on true borders (the
    # 128 x 72 tiny camera is coarse: 0.40 measured; 0.72 on the 480 x 270 demo world), far more
    # than through a wrong pose
    reader = SequenceReader(tiny)
    _, gt_lines = world_ground_truth(load_ground_truth(tiny / "sim"))
    precision, total = _line_precision(reader, submaps, gt_lines)
    assert total > 20.0 and precision > 0.3
    for lateral, yaw in ((3.0, 0.0), (-3.0, 0.0), (0.0, 0.3)):
        wrong, _ = _line_precision(reader, submaps, gt_lines, lateral, yaw)
        assert wrong < 0.6 * precision


def test_geometries_are_kept_only_when_asked(tiny: Path, submaps) -> None:
    """A mapper that keeps every submap's flattened points (map-ground plots) and one that does
    not (the localizer: constant memory on a long drive) make the same submaps."""
    reader = SequenceReader(tiny)
    keeping = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime), keep_geometries=True)
    kept = keeping.map_sequence(reader)
    assert len(kept) == len(submaps) == keeping.num_submaps > 0
    assert len(keeping.geometries) == len(kept)
    assert GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime)).geometries is None
    for a, b, geometry in zip(kept, submaps, keeping.geometries):
        assert a.index == b.index and a.time == b.time
        assert torch.equal(a.primitives.points_xy, b.primitives.points_xy)
        assert torch.equal(a.primitives.line_endpoints, b.primitives.line_endpoints)
        np.testing.assert_array_equal(geometry.segment_ids, a.segment_ids.cpu().numpy())


def test_batched_and_frame_by_frame_agree(tiny: Path) -> None:
    reader = SequenceReader(tiny)
    runtime = resolve_runtime(CFG.runtime)
    frames = [reader[i] for i in range(10)]
    batched = GroundMapper.from_config(CFG, reader.camera, runtime)
    batched.add_frames(frames)
    single = GroundMapper.from_config(CFG, reader.camera, runtime)
    for f in frames:
        single.add_frame(f)
    assert batched.tracker.segments.keys() == single.tracker.segments.keys()
    for sid, seg in batched.tracker.segments.items():
        np.testing.assert_array_equal(seg.keys, single.tracker.segments[sid].keys)
    with pytest.raises(ValueError):
        single.add_frame(frames[3])  # time must increase


def test_frames_in_threads_give_the_same_segments(tiny: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Per-frame segmentation and 3D work in 4 threads equal the plain loop, bitwise."""
    from meridian_torch.core import parallel
    from meridian_torch.mapping import ground_observations
    from meridian_torch.perception.classical import segmenter

    reader = SequenceReader(tiny)
    frames = [reader[i] for i in range(12)]
    trackers = []
    for threads in (1, 4):
        def fixed(fn, items, threads=threads):
            return parallel.thread_map(fn, items, threads)

        monkeypatch.setattr(ground_observations, "thread_map", fixed)
        monkeypatch.setattr(segmenter, "thread_map", fixed)
        mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
        mapper.add_frames(frames)
        trackers.append(mapper.tracker)
    plain, threaded = trackers
    assert plain.segments.keys() == threaded.segments.keys() and len(plain.segments) > 0
    for sid, seg in plain.segments.items():
        np.testing.assert_array_equal(seg.keys, threaded.segments[sid].keys)
        np.testing.assert_array_equal(seg.points, threaded.segments[sid].points)
        assert torch.equal(seg.descriptor_sum, threaded.segments[sid].descriptor_sum)


def test_submap_file_roundtrip(tmp_path: Path, submaps) -> None:
    path = tmp_path / "submaps.mts"
    save_ground_submaps(submaps, path, config={"ground_map": CFG.ground_map.model_dump(mode="json")})
    loaded, header = load_ground_submaps(path)
    assert header["num_submaps"] == len(submaps) == len(loaded)
    for a, b in zip(submaps, loaded):
        assert (a.index, a.time, a.path_length_m) == (b.index, b.time, b.path_length_m)
        np.testing.assert_array_equal(a.T_odom_base, b.T_odom_base)
        for name in ("points_xy", "line_endpoints", "line_kinds", "point_descriptors", "line_segment_ids"):
            assert torch.equal(getattr(a.primitives, name).cpu(), getattr(b.primitives, name))
        assert torch.equal(a.frame_descriptors.float().cpu(), b.frame_descriptors)
        assert torch.equal(a.segment_ids.cpu(), b.segment_ids)
    # corruption is detected
    with np.load(path) as npz:
        arrays = {k: npz[k].copy() for k in npz.files}
    arrays["time"][0] += 1.0
    bad = tmp_path / "bad.mts"
    with open(bad, "wb") as fh:
        np.savez(fh, **arrays)
    with pytest.raises(SubmapFileError):
        load_ground_submaps(bad)


def test_empty_submap_file_roundtrip(tmp_path: Path) -> None:
    path = tmp_path / "none.mts"
    save_ground_submaps([], path, descriptor_dim=5, global_descriptor_dim=7)
    loaded, header = load_ground_submaps(path)
    assert loaded == [] and header["num_submaps"] == 0


def test_cli_map_ground_writes_submaps_and_plots(tiny: Path, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from meridian_torch.cli import app

    out = tmp_path / "ground"
    result = CliRunner().invoke(app, ["map-ground", str(tiny), "--out", str(out), "-c", str(CONFIG_DIR / "tiny.yaml")])
    assert result.exit_code == 0, result.output
    loaded, header = load_ground_submaps(out / "submaps.mts")
    assert len(loaded) >= 1 and header["config"]["ground_map"]["submap_radius_m"] == 40.0
    assert sorted(p.name for p in (out / "plots").glob("*.png")) == [f"submap_{s.index:03d}.png" for s in loaded]
    assert (out / "config.yaml").is_file() and (out / "run.json").is_file()
    bad = CliRunner().invoke(app, ["map-ground", str(tmp_path / "missing"), "--out", str(out)])
    assert bad.exit_code == 1 and "error:" in bad.output


def test_ground_mapping_stages_are_timed_when_recorded(tiny: Path) -> None:
    from meridian_torch.core.timing import record_stages

    reader = SequenceReader(tiny)
    mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
    with record_stages() as times:
        mapper.add_frames([reader[i] for i in range(4)])
    assert {"global descriptors", "segmentation", "segment descriptors", "observations", "tracking",
            "submaps"} <= set(times.seconds)
    assert times.calls["tracking"] == 4 and times.calls["segmentation"] == 1  # one batch, four frames


def test_perceiving_a_batch_ahead_gives_the_plain_loops_submaps(tiny: Path, submaps) -> None:
    """map_ground decodes two batches ahead in a reader thread and perceives one ahead in another
    (`perceived_batches`); the submaps are bitwise those of a plain add_frames loop over the same
    batches."""
    reader = SequenceReader(tiny)
    mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
    plain = _plain_loop(mapper, reader, range(len(reader)))
    assert len(submaps) >= 2
    _assert_same_submaps(plain, submaps)
    for a, b in zip(plain, submaps):
        assert torch.equal(a.frame_descriptors, b.frame_descriptors)


def test_the_pipeline_runs_torch_single_threaded_and_restores_it(tiny: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """While `perceived_batches` runs, torch has one thread in the perceivers and in the caller
    (the pipeline's own threads fill the cores) and each perceiver's per-frame pool takes its
    share of the caller's threads; the caller's count comes back when the generator ends and when
    it is closed early."""
    from meridian_torch.core.parallel import cpu_threads
    from meridian_torch.mapping import ground_map

    reader = SequenceReader(tiny)
    mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
    perceive, in_perceivers = mapper.perceive, []

    def counting(frames):
        in_perceivers.append((torch.get_num_threads(), cpu_threads()))
        return perceive(frames)

    monkeypatch.setattr(mapper, "perceive", counting)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        in_caller = [torch.get_num_threads() for _ in ground_map.perceived_batches(mapper, reader, len(reader))]
        assert torch.get_num_threads() == 3
        # torch at 1 everywhere; each perceiver's per-frame pool takes its share of the 3 threads
        share = max(1, 3 // CFG.ground_map.perception_threads)
        assert len(in_caller) >= 2 and set(in_caller) == {1} and set(in_perceivers) == {(1, share)}
        fresh = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
        batches = ground_map.perceived_batches(fresh, reader, len(reader))
        next(batches)
        assert torch.get_num_threads() == 1
        batches.close()
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_a_frame_that_cannot_be_decoded_stops_the_pipeline_with_its_file(tiny: Path, tmp_path: Path) -> None:
    """The reader thread's error reaches the caller (not a hang, not a skipped frame) and names the file."""
    import shutil

    from meridian_torch.errors import SequenceFormatError

    seq = tmp_path / "seq"
    shutil.copytree(tiny, seq)
    index = CFG.ground_map.batch_size + 1  # in the second batch, decoded while the first is perceived
    row = (seq / "ground" / "frames.csv").read_text().splitlines()[1 + index]  # timestamp,rgb,depth
    rgb_path = seq / "ground" / row.split(",")[1]
    rgb_path.write_bytes(b"not a png")
    with pytest.raises(SequenceFormatError, match=rgb_path.name):
        map_ground(SequenceReader(seq), CFG, resolve_runtime(CFG.runtime))


def test_fast_tracking_gives_the_plain_trackers_submaps(tiny: Path, submaps) -> None:
    """The whole tiny sequence through the plain tracker (every occluded voxel against every point,
    IoM per pair, eager centroids and extents): the same segments on every frame and the same
    submaps as map_ground, bitwise."""
    from tests.test_ground_tracking import PlainTracker, assert_same_segments

    reader = SequenceReader(tiny)
    fast = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
    plain = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime))
    plain.tracker = PlainTracker(CFG.ground_map.tracking)
    made = {"fast": [], "plain": []}
    for start in range(0, len(reader), CFG.ground_map.batch_size):
        batch = fast.perceive([reader[i] for i in range(start, min(start + CFG.ground_map.batch_size, len(reader)))])
        made["fast"] += fast.integrate(batch)
        made["plain"] += plain.integrate(batch)
        assert_same_segments(fast.tracker.segments, plain.tracker.segments)
    made["fast"] += fast.finish()
    made["plain"] += plain.finish()
    assert len(made["fast"]) == len(made["plain"]) == len(submaps) >= 2
    for a, b, c in zip(made["fast"], made["plain"], submaps):
        assert a.time == b.time == c.time
        for name in a.primitives.__dataclass_fields__:
            assert torch.equal(getattr(a.primitives, name), getattr(b.primitives, name)), name
            assert torch.equal(getattr(a.primitives, name), getattr(c.primitives, name)), name
        assert torch.equal(a.segment_ids, b.segment_ids)


def _first_of_each_interval(times: list[float], rate_hz: float) -> list[bool]:
    """The rule spelled out: walk the clock's intervals from the first frame and map a frame when
    it is the first to land in its interval."""
    origin, seen, out = times[0], set(), []
    for t in times:
        k = 0
        while origin + (k + 1) / rate_hz <= t + 1e-9:
            k += 1
        out.append(k not in seen)
        seen.add(k)
    return out


@settings(max_examples=60, deadline=None)
@given(
    gaps=st.lists(st.floats(0.01, 0.7), min_size=1, max_size=60),
    rate_hz=st.floats(0.5, 30.0),
    cut=st.integers(0, 60),
)
def test_the_mapper_takes_the_first_frame_of_each_interval_of_its_clock(tiny: Path, gaps, rate_hz, cut) -> None:
    times = np.cumsum([3.0, *gaps])  # any start time: the clock starts at the first frame
    mapper = GroundMapper.from_config(
        load_config(CONFIG_DIR / "tiny.yaml", [f"ground_map.mapping_rate_hz={rate_hz!r}"]),
        SequenceReader(tiny).camera, resolve_runtime(CFG.runtime),
    )
    cut = min(cut, len(times))  # offered in two calls: the clock carries over
    due = np.concatenate([mapper.due(times[:cut]), mapper.due(times[cut:])])
    assert due.tolist() == _first_of_each_interval(times.tolist(), rate_hz)
    assert due[0] and due.sum() <= np.floor((times[-1] - times[0]) * rate_hz + 1e-6) + 1
    assert frames_to_map(times, times[0], None, None).all()
    with pytest.raises(ValueError, match="strictly increasing"):
        mapper.due(times[-1:])


def test_frames_above_the_mapping_rate_are_neither_decoded_nor_mapped(tiny: Path) -> None:
    """At half the tiny sequence's frame rate, map_ground reads and maps only the frames due, and its
    submaps are bitwise those of a mapper that maps every frame fed only those."""

    class Counting(SequenceReader):
        def __init__(self, path: Path) -> None:
            super().__init__(path)
            self.read: list[int] = []

        def __getitem__(self, index: int):
            self.read.append(index)
            return super().__getitem__(index)

    reader = Counting(tiny)
    rate = 0.5 / float(np.median(np.diff(reader.frame_times)))
    half = load_config(CONFIG_DIR / "tiny.yaml", [f"ground_map.mapping_rate_hz={rate!r}"])
    due = np.flatnonzero(frames_to_map(reader.frame_times, reader.frame_times[0], None, rate))
    assert len(reader) * 0.4 < len(due) < len(reader) * 0.6
    skipping = map_ground(reader, half, resolve_runtime(half.runtime))
    assert sorted(reader.read) == due.tolist()

    every = load_config(CONFIG_DIR / "tiny.yaml", ["ground_map.mapping_rate_hz=null"])
    mapper = GroundMapper.from_config(every, reader.camera, resolve_runtime(every.runtime))
    assert len(skipping) >= 1
    _assert_same_submaps(_plain_loop(mapper, reader, due), skipping)


def test_a_mapper_without_frame_descriptors_makes_the_same_submaps(tiny: Path, submaps) -> None:
    """Frame descriptors only feed global place recognition; leaving them out changes nothing else."""
    from meridian_torch.core.timing import record_stages

    reader = SequenceReader(tiny)
    mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime), frame_descriptors=False)
    with record_stages() as times:
        bare = mapper.map_sequence(reader)
    assert "global descriptors" not in times.seconds
    assert len(submaps) >= 2
    _assert_same_submaps(bare, submaps)
    assert mapper.global_describer is None  # nothing to describe frames with, nothing loaded for it
    assert all(len(a.frame_descriptors) == 0 < len(b.frame_descriptors) for a, b in zip(bare, submaps))


def _spaced_submaps(reader: SequenceReader, spacing: dict[str, float]) -> list[tuple[float, float]]:
    """(path length of the frame that made it, of its centre) of every submap of a mapper spaced by
    `spacing` from the first frame on (as after a fix), fed one frame at a time."""
    mapper = GroundMapper.from_config(CFG, reader.camera, resolve_runtime(CFG.runtime), frame_descriptors=False)
    mapper.trigger.use_spacing(SubmapSpacingConfig(**spacing))
    made = []
    for i in range(len(reader)):
        made += [(mapper.frames[-1].path_length_m, s.path_length_m) for s in mapper.add_frames([reader[i]])]
    return made


def test_a_submap_centre_trails_the_robot_by_at_most_the_bound(tiny: Path) -> None:
    """With few new segments their median time lags and a postponed submap waits for it;
    `max_centre_lag_m` moves such a centre up to that much travel behind the newest frame."""
    reader = SequenceReader(tiny)
    spacing = {"trigger_path_m": 2.0, "min_interval_s": 0.0, "min_path_m": 2.0}
    free = _spaced_submaps(reader, spacing)
    lags = [made - centre for made, centre in free]
    bound = 0.5 * max(lags)
    assert bound > 0.0
    bounded = _spaced_submaps(reader, {**spacing, "max_centre_lag_m": bound})
    assert bounded and all(made - centre <= bound + 1e-9 for made, centre in bounded)
