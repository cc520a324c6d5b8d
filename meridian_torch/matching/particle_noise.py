"""Counter-based randomness of the particle sampler: splitmix64 words per (patch seed, step,
particle, coordinate) and a fixed table of standard normals read in per-patch slabs, so that a
patch's draws depend only on its own seed, never on the batch it travels in or its padding."""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from meridian_torch.matching.kernels import (
    initial_particles,
    mix_words,
    particle_words,
    signed_sigmas,
    uniform_words,
)

__all__ = [
    "ROW", "add_noise_", "circular_table", "initial_positions", "mix", "patch_seeds", "row_words", "slab_table",
    "step_noise", "uniform",
]

# Signed int64 constants (torch has no uint64 arithmetic); products and sums wrap mod 2^64.
_GOLDEN = 0x9E3779B97F4A7C15 - (1 << 64)
ROW = 0xD1B54A32D192ED03 - (1 << 64)
# Fixed seed (independent of the caller's generator) of the noise table; the table is long
# enough that two patches' slabs rarely overlap.
_TABLE_SEED = 0x7AB1E
_TABLE_SIZE = 1 << 20


def srl(z: Tensor, shift: int) -> Tensor:
    """Logical right shift of int64 (torch's >> is arithmetic)."""
    return (z >> shift) & ((1 << (64 - shift)) - 1)


def mix(z: Tensor) -> Tensor:
    """splitmix64 finaliser on int64 tensors: a bijective, well-avalanched 64-bit hash (computed
    on the CPU in one compiled pass: as ~10 torch ops over a match's million words it took 3 %
    of the match)."""
    return torch.from_numpy(mix_words(_cpu_words(z)).view(np.int64)).to(z.device)


def _cpu_words(z: Tensor) -> np.ndarray:
    """int64 words as a uint64 array on the CPU, for the compiled kernels."""
    return z.detach().to("cpu", torch.int64).contiguous().numpy().view(np.uint64)


def wrap64(value: int) -> int:
    """A Python int reduced to the signed int64 range (two's complement)."""
    return (value + (1 << 63)) % (1 << 64) - (1 << 63)


def row_words(seeds: Tensor, step: int, n_particles: int) -> Tensor:
    """(P,) seeds -> (P, N) int64 random words of iteration `step` (one per particle)."""
    return step_words(seeds, [step], n_particles)[0]


def step_words(seeds: Tensor, steps: list[int], n_particles: int) -> Tensor:
    """(P,) seeds -> (S, P, N) int64 random words of the iterations `steps` (one per particle)."""
    step_keys = torch.tensor([wrap64((step + 2) * _GOLDEN) for step in steps], dtype=torch.int64, device=seeds.device)
    base = mix(seeds[None, :] + step_keys[:, None])
    # mix(base[..., None] + arange(N) * ROW) in one compiled pass (three torch passes cost more).
    words = particle_words(_cpu_words(base).reshape(-1), n_particles, np.uint64(ROW % (1 << 64)))
    return torch.from_numpy(words.view(np.int64)).reshape(*base.shape, n_particles).to(seeds.device)


def initial_positions(seeds: Tensor, validf: Tensor, n_particles: int) -> Tensor:
    """The sampler's start (P, m, N) for seeds (P,): U[0, 1) (`uniform`) of the words
    mix(row_words(seeds, -1, N)[p, n] ^ mix(i + ROW)) in validf's dtype, times validf (P, m);
    in one compiled pass over the P x m x N words."""
    coord_keys = mix(torch.arange(validf.shape[1], dtype=torch.int64) + ROW)
    words = _cpu_words(row_words(seeds, -1, n_particles))
    x = initial_particles(words, _cpu_words(coord_keys), validf.detach().cpu().contiguous().numpy())
    return torch.from_numpy(x).to(validf.device)


def uniform(z: Tensor, dtype: torch.dtype) -> Tensor:
    """int64 words -> U[0, 1) from their top 53 bits in float64, rounded to dtype (float32 may give
    1.0); computed on the CPU in one compiled pass (four torch passes over a match's million
    words cost 2 %)."""
    out = torch.empty(z.shape, dtype=dtype)
    uniform_words(_cpu_words(z), out.numpy())
    return out.to(z.device)


@functools.lru_cache(maxsize=4)
def noise_table(dtype: torch.dtype, device: torch.device) -> Tensor:
    """_TABLE_SIZE fixed standard normals (seeded once, independent of the caller) followed by
    their first _TABLE_SIZE - 1 again, so that every window of up to _TABLE_SIZE entries can be
    read circularly from any offset. Made once per process: drawing it took a tenth of a match."""
    gen = torch.Generator(device="cpu").manual_seed(_TABLE_SEED)
    table = torch.randn(_TABLE_SIZE, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)
    return torch.cat([table, table[:-1]])


def circular_table(width: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """1-D noise table from which the slab at any offset r < _TABLE_SIZE is entries r .. r + width - 1."""
    table = noise_table(dtype, device)
    if width > _TABLE_SIZE:
        table = table[:_TABLE_SIZE].repeat(2 + width // _TABLE_SIZE)
    return table[: _TABLE_SIZE + width - 1]


def slab_table(width: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(_TABLE_SIZE, width) view of the circular noise table: row r = entries r .. r + width - 1."""
    return circular_table(width, dtype, device).unfold(0, width, 1)


def step_noise(seeds: Tensor, sigmas: list[float], n_particles: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The noise of every step t (sigma_t = sigmas[t]) for patches with seeds (P,): the offset of
    each patch's slab in the table (T, P) int64, from its first particle's word, and the scale of
    each particle (T, P, N), sigma_t with a random sign per particle, so that two patches whose
    slabs overlap in the table still differ.

    Patch p's noise of step t, coordinate i, particle n is slab[offsets[t, p]][i N + n] x
    scale[t, p, n]: a coordinate sees the same numbers whatever the padded width m. Hashing every
    entry would cost as much as the drift."""
    words = step_words(seeds, list(range(len(sigmas))), n_particles)
    offsets = srl(words[..., 0], 1) % _TABLE_SIZE
    T, P, N = words.shape
    scale = signed_sigmas(_cpu_words(words).reshape(T, P * N), torch.tensor(sigmas, dtype=dtype).numpy())
    return offsets, torch.from_numpy(scale).reshape(words.shape).to(seeds.device)


def add_noise_(g: Tensor, slabs: Tensor, offsets: Tensor, scale: Tensor) -> Tensor:
    """g (P, m, N) += the slabs at `offsets` (P,) of `slab_table` x scale (P, N), in place."""
    n_patches, m, n = g.shape
    return g.addcmul_(slabs.index_select(0, offsets).view(n_patches, m, n), scale[:, None, :])


def patch_seeds(n_patches: int, generator: torch.Generator) -> Tensor:
    """(P,) int64 per-patch seeds drawn from `generator` (the only use of the generator)."""
    return torch.randint(0, 1 << 62, (n_patches,), generator=generator, device=generator.device)
