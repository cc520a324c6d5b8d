"""PrimitiveBatch padding: trimming keeps every patch's content and drops only unused padding; moving
batches between devices and dtypes; a set as NumPy arrays and back."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given
from hypothesis import strategies as st

from meridian_torch.types import PrimitiveSet, stack_primitive_sets


def _set(n_points: int, n_lines: int, seed: int) -> PrimitiveSet:
    gen = torch.Generator().manual_seed(seed)
    return PrimitiveSet(
        torch.rand(n_points, 2, generator=gen), torch.rand(n_points, 4, generator=gen), torch.arange(n_points),
        torch.rand(n_lines, 2, 2, generator=gen), torch.randint(0, 3, (n_lines,), generator=gen),
        torch.rand(n_lines, 4, generator=gen), torch.arange(n_lines),
    )


@given(st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), min_size=1, max_size=5), st.integers(0, 3))
def test_trimmed_batch_keeps_every_patch_and_drops_unused_padding(sizes: list[tuple[int, int]], extra: int) -> None:
    sets = [_set(n_p, n_l, k) for k, (n_p, n_l) in enumerate(sizes)]
    batch = stack_primitive_sets(sets)
    # Padding beyond every patch, as a batch selected from a larger one has.
    padded = type(batch)(**{
        name: torch.cat([t, t.new_zeros((len(t), extra) + tuple(t.shape[2:]))], 1)
        for name, t in vars(batch).items()
    })
    trimmed = padded.select(torch.arange(len(sets))).trimmed()
    max_points, max_lines = max(n for n, _ in sizes), max(n for _, n in sizes)
    assert trimmed.points_xy.shape[1] == max(max_points, min(1, padded.points_xy.shape[1]))
    assert trimmed.line_endpoints.shape[1] == max(max_lines, min(1, padded.line_endpoints.shape[1]))
    used_points, used_lines = padded.used_lengths()
    assert used_points.tolist() == [n for n, _ in sizes] and used_lines.tolist() == [n for _, n in sizes]
    for k in range(len(sets)):
        a, b = trimmed.unbatch(k), padded.unbatch(k)
        for name in ("points_xy", "point_descriptors", "line_endpoints", "line_kinds", "line_descriptors"):
            assert torch.equal(getattr(a, name), getattr(b, name))


def test_trimming_keeps_entries_after_a_gap_in_the_valid_mask() -> None:
    batch = stack_primitive_sets([_set(4, 3, 0), _set(2, 1, 1)])
    valid = batch.point_valid.clone()
    valid[0, 2] = False  # patch 0 keeps 3 valid points, the last at index 3
    gapped = type(batch)(**{**vars(batch), "point_valid": valid})
    assert gapped.used_lengths()[0].tolist() == [4, 2]
    assert gapped.trimmed().points_xy.shape[1] == 4


def test_moving_a_batch_changes_floating_dtypes_only_and_keeps_values() -> None:
    batch = stack_primitive_sets([_set(4, 3, 0), _set(2, 1, 1)])
    same = batch.to(device="cpu")
    assert all(getattr(same, n) is getattr(batch, n) for n in vars(batch))  # nothing copied
    wide = batch.to(dtype=torch.float64)
    for name, t in vars(batch).items():
        moved = getattr(wide, name)
        assert moved.dtype == (torch.float64 if t.is_floating_point() else t.dtype)
        assert torch.equal(moved.to(t.dtype), t)


@given(st.integers(0, 5), st.integers(0, 5), st.integers(0, 3))
def test_primitive_set_arrays_round_trip(n_points: int, n_lines: int, seed: int) -> None:
    # Part files and worker processes carry a set as NumPy arrays by field name.
    prims = _set(n_points, n_lines, seed)
    arrays = prims.arrays()
    assert set(arrays) == set(vars(prims)) and all(isinstance(a, np.ndarray) for a in arrays.values())
    back = PrimitiveSet.from_arrays(arrays)
    for name, tensor in vars(prims).items():
        assert getattr(back, name).dtype == tensor.dtype and torch.equal(getattr(back, name), tensor)
