"""Weight-free coarse global search: every map position and yaw scored for one ground submap.

The aerial map's points and sampled line points are rasterised once into per-class occupancy
grids (classes: descriptor clusters, `CoarseSearchConfig.classes`), blurred and Fourier
transformed in square tiles. A submap is rasterised around its centre at every yaw of a grid and
correlated with the whole map by FFT, tile by tile (overlap-save: each tile's circular correlation
is exact away from its first side - 1 rows and columns, which the tiles' overlap covers),
normalised per window (Pearson correlation over the submap's disk),
giving a (yaws, H, W) score volume over (T_world_odom yaw, submap centre cell). Successive
submaps share T_world_odom up to odometry drift, so a chain of submaps is scored jointly by a
recursive filter: the previous chain volume, max-pooled by the drift slack, is shifted by the
odometry step (rotated by each yaw) and added with a decay. A patch scores the best value of the
cells it owns (cells go to the nearest patch centre among the patches containing them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from meridian_torch.config.matching import CoarseSearchConfig
from meridian_torch.core.parallel import cpu_threads, thread_map
from meridian_torch.geometry.se2 import rotation_matrix, wrap_line_angle
from meridian_torch.matching.place_recognition.coarse_kernels import best_yaws, chain_yaws
from meridian_torch.types import PrimitiveBatch, PrimitiveSet

__all__ = [
    "CoarseMap",
    "CoarsePriors",
    "CoarseSearch",
    "build_coarse_map",
    "chain_scores",
    "descriptor_classes",
    "patch_priors",
    "submap_scores",
]

_RASTER_PATCHES = 1024  # patches whose primitives are sampled and rasterised at once
_OWNER_BLOCK = 32  # cells per side of the blocks whose owners are found together


@dataclass(frozen=True)
class CoarseMap:
    """The aerial map prepared for the coarse search (built once per map).

    Cell (row, col) covers x in origin_x + col * cell_m + [0, cell_m), y likewise with row.
    """

    origin_xy: tuple[float, float]
    cell_m: float
    shape: tuple[int, int]  # (H, W)
    tile_size: int  # F: side of the square tiles the correlations are computed in (overlap-save)
    tile_spectra: torch.Tensor  # (C, T, F, F // 2 + 1) rfft2 of the blurred class grids' tiles, T = rows x cols
    tile_layout: tuple[int, int]  # (rows, cols) of tiles; tile (i, j) yields the cells from (i, j) * (F - side + 1)
    window_energy: torch.Tensor  # (H, W) sum of squared deviations of the grid in the disk around each cell
    cell_patch: torch.Tensor  # (H * W,) int64 patch owning each cell, -1 off the map
    class_centres: torch.Tensor  # (C, D) unit descriptor cluster centres (C = 1: zeros)
    n_patches: int


@dataclass(frozen=True)
class CoarsePriors:
    """Per patch (P,): best score, the yaw of T_world_odom and the submap centre where it was found."""

    score: torch.Tensor  # (P,) -inf for patches owning no cell
    yaw: torch.Tensor  # (P,) radians
    centre_xy: torch.Tensor  # (P, 2) metres, map frame


def descriptor_classes(descriptors: torch.Tensor, class_centres: torch.Tensor) -> torch.Tensor:
    """(N, D) descriptors -> (N,) int64 index of the most cosine-similar class centre."""
    if len(class_centres) == 1:
        return torch.zeros(len(descriptors), dtype=torch.int64, device=descriptors.device)
    return (torch.nn.functional.normalize(descriptors.float(), dim=-1) @ class_centres.T).argmax(-1)


def _class_centres(primitives: PrimitiveBatch, n_classes: int, seed: int) -> torch.Tensor:
    """Spherical k-means of the valid point and line descriptors (farthest-point start from a
    seeded first centre, fixed iterations)."""
    if n_classes == 1:  # no clustering: no copy of every descriptor either
        return torch.zeros(1, primitives.point_descriptors.shape[-1])
    x = torch.nn.functional.normalize(torch.cat([
        primitives.point_descriptors[primitives.point_valid], primitives.line_descriptors[primitives.line_valid]
    ]).float(), dim=-1)
    if len(x) == 0:
        return x.new_zeros(1, x.shape[1])
    k = min(n_classes, len(x))
    first = int(torch.randint(len(x), (1,), generator=torch.Generator().manual_seed(seed)))
    centres = x[first : first + 1]
    for _ in range(1, k):  # k is a handful: start from well-separated centres
        centres = torch.cat([centres, x[(x @ centres.T).amax(1).argmin()][None]])
    for _ in range(20):
        labels = (x @ centres.T).argmax(1)
        sums = torch.zeros_like(centres).index_add_(0, labels, x)
        centres = torch.where(sums.norm(dim=1, keepdim=True) > 0, torch.nn.functional.normalize(sums, dim=1), centres)
    return centres


def _line_samples(ends: torch.Tensor, step_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2, 2) segments -> points every <= step_m along them (M, 2) and their segment (M,)."""
    length = (ends[:, 1] - ends[:, 0]).norm(dim=-1)
    n = (length / step_m).ceil().long().clamp_min(1) + 1
    seg = torch.repeat_interleave(torch.arange(len(ends), device=ends.device), n)
    k = torch.arange(len(seg), device=ends.device) - (torch.cumsum(n, 0) - n)[seg]
    t = (k.to(ends.dtype) / (n[seg] - 1).to(ends.dtype))[:, None]
    return ends[seg, 0] + t * (ends[seg, 1] - ends[seg, 0]), seg


def _primitive_points(
    points_xy: torch.Tensor, point_desc: torch.Tensor, line_ends: torch.Tensor, line_desc: torch.Tensor,
    centres: torch.Tensor, step_m: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points and sampled line points (M, 2), their descriptor classes (M,) and line angles (M,),
    NaN for points."""
    samples, seg = _line_samples(line_ends.float(), step_m)
    xy = torch.cat([points_xy.float(), samples])
    cls = torch.cat([descriptor_classes(point_desc, centres), descriptor_classes(line_desc, centres)[seg]])
    d = line_ends[:, 1] - line_ends[:, 0]
    angle = torch.atan2(d[:, 1], d[:, 0]).float()[seg]
    return xy, cls, torch.cat([torch.full((len(points_xy),), float("nan")), angle])


def _channels(cls: torch.Tensor, angle: torch.Tensor, cfg: CoarseSearchConfig) -> torch.Tensor:
    """Raster channel of each sample: descriptor class x (one point channel + line orientation bins
    over [0, pi)); `angle` may carry a leading yaw axis (it is the world angle)."""
    bins = cfg.orientation_bins
    if bins == 0:
        return cls.expand(angle.shape)
    per_class = 1 + bins
    line_bin = 1 + (wrap_line_angle(torch.nan_to_num(angle)) / math.pi * bins).long().clamp_max(bins - 1)
    return cls * per_class + torch.where(torch.isnan(angle), 0, line_bin)


def _n_channels(n_classes: int, cfg: CoarseSearchConfig) -> int:
    return n_classes * (1 + cfg.orientation_bins) if cfg.orientation_bins else n_classes


def _rasterise(xy: torch.Tensor, cls: torch.Tensor, origin: tuple[float, float], cell_m: float,
               shape: tuple[int, int], n_classes: int) -> torch.Tensor:
    """(..., M, 2) points with (M,) classes -> (..., C, H, W) occupancy (1 where a point falls)."""
    h, w = shape
    col = ((xy[..., 0] - origin[0]) / cell_m).floor().long()
    row = ((xy[..., 1] - origin[1]) / cell_m).floor().long()
    lead = xy.shape[:-2]
    batch = torch.arange(math.prod(lead), device=xy.device).view(*lead, 1)
    flat = ((batch * n_classes + cls) * h + row) * w + col
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out = torch.zeros(math.prod(lead) * n_classes * h * w, device=xy.device)
    out.index_fill_(0, flat[ok], 1.0)
    return out.view(*lead, n_classes, h, w)


def _blur(x: torch.Tensor, sigma_cells: float) -> torch.Tensor:
    """Separable Gaussian blur of the last two axes."""
    if sigma_cells <= 0:
        return x
    r = int(math.ceil(3 * sigma_cells))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=x.dtype, device=x.device) / sigma_cells) ** 2)
    k = k / k.sum()
    y = x.reshape(-1, 1, *x.shape[-2:])
    y = torch.nn.functional.conv2d(y, k.view(1, 1, 1, -1), padding=(0, r))
    y = torch.nn.functional.conv2d(y, k.view(1, 1, -1, 1), padding=(r, 0))
    return y.reshape(x.shape)


def _fast_size(n: int) -> int:
    """Smallest m >= n whose only prime factors are 2, 3 and 5 (fast FFT lengths)."""
    while True:
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


def _radius_cells(cfg: CoarseSearchConfig) -> int:
    return int(math.ceil(cfg.radius_m / cfg.cell_m))


def _disk(cfg: CoarseSearchConfig) -> torch.Tensor:
    r = _radius_cells(cfg)
    u = torch.arange(-r, r + 1)
    return ((u[:, None] ** 2 + u[None] ** 2) <= r * r).float()


def _cell_owners(origin: tuple[float, float], cell_m: float, shape: tuple[int, int], bounds: torch.Tensor
                 ) -> torch.Tensor:
    """(H * W,) int64 patch owning each cell: the nearest centre among the patches (`bounds` (P, 4))
    containing the cell centre, the lowest index on ties, -1 for none. Found block by block among
    the patches overlapping the block (the others contain none of its cells), so the cost grows
    with the map's area, not with area x patches."""
    h, w = shape
    cy = origin[1] + (torch.arange(h, dtype=torch.float64) + 0.5) * cell_m
    cx = origin[0] + (torch.arange(w, dtype=torch.float64) + 0.5) * cell_m
    patch_centres = torch.stack([(bounds[:, 0] + bounds[:, 1]) / 2, (bounds[:, 2] + bounds[:, 3]) / 2], -1)
    owner = torch.full((h, w), -1, dtype=torch.int64)
    for r0 in range(0, h, _OWNER_BLOCK):
        y = cy[r0 : r0 + _OWNER_BLOCK]
        in_rows = (bounds[:, 2] <= y[-1]) & (bounds[:, 3] >= y[0])
        for c0 in range(0, w, _OWNER_BLOCK):
            x = cx[c0 : c0 + _OWNER_BLOCK]
            candidates = torch.nonzero(in_rows & (bounds[:, 0] <= x[-1]) & (bounds[:, 1] >= x[0])).flatten()
            if len(candidates) == 0:
                continue
            b = bounds[candidates]
            gy, gx = torch.meshgrid(y, x, indexing="ij")
            cells = torch.stack([gx.reshape(-1), gy.reshape(-1)], -1)
            cell_x, cell_y = cells[:, 0:1], cells[:, 1:2]
            inside = (cell_x >= b[:, 0]) & (cell_x <= b[:, 1]) & (cell_y >= b[:, 2]) & (cell_y <= b[:, 3])
            dist = torch.cdist(cells, patch_centres[candidates], compute_mode="donot_use_mm_for_euclid_dist")
            dist = dist.masked_fill(~inside, float("inf"))  # exact distances: ties go to the lowest index
            best = torch.where(inside.any(1), candidates[dist.argmin(1)], -1)
            owner[r0 : r0 + len(y), c0 : c0 + len(x)] = best.view(len(y), len(x))
    return owner.reshape(-1)


def _map_grid(primitives: PrimitiveBatch, bounds: torch.Tensor, centres: torch.Tensor, cfg: CoarseSearchConfig
              ) -> tuple[torch.Tensor, tuple[float, float]]:
    """The blurred class grids (C, H, W) of the map's primitives and the grid's origin."""
    margin = cfg.radius_m
    origin = (float(bounds[:, 0].min()) - margin, float(bounds[:, 2].min()) - margin)
    h = int(math.ceil((float(bounds[:, 3].max()) + margin - origin[1]) / cfg.cell_m))
    w = int(math.ceil((float(bounds[:, 1].max()) + margin - origin[0]) / cfg.cell_m))
    n_channels = _n_channels(len(centres), cfg)
    occupancy = torch.zeros(n_channels, h, w)
    for first in range(0, len(primitives), _RASTER_PATCHES):  # a union: chunks only bound the samples' memory
        part = primitives.select(slice(first, first + _RASTER_PATCHES))
        xy, cls, angle = _primitive_points(
            part.points_xy[part.point_valid], part.point_descriptors[part.point_valid],
            part.line_endpoints[part.line_valid], part.line_descriptors[part.line_valid], centres, cfg.cell_m / 2,
        )
        torch.maximum(occupancy, _rasterise(xy, _channels(cls, angle, cfg), origin, cfg.cell_m, (h, w), n_channels),
                      out=occupancy)
    return _blur(occupancy, cfg.blur_cells), origin


def _tile_size(shape: tuple[int, int], side: int, n_channels: int) -> int:
    """Tile side F (a fast FFT length) for correlating a map of `shape` with `side`-wide kernels of
    `n_channels` tile by tile: the least estimated work per yaw, F^2 x (2.5 log2 F per inverse FFT
    of a tile and per half FFT of a channel's kernel + 4 per channel and tile for the products), each
    tile yielding F - side + 1 cells a side."""
    def work(f: int) -> float:
        tiles = math.ceil(shape[0] / (f - side + 1)) * math.ceil(shape[1] / (f - side + 1))
        return f * f * (2.5 * math.log2(f) * (tiles + n_channels / 2) + 4 * n_channels * tiles)

    sizes = {_fast_size(n) for n in range(2 * side, 2 * (max(shape) + side), 8)}
    return min(sorted(sizes), key=work)


def _tile_spectra(grid: torch.Tensor, side: int, tile: int) -> tuple[torch.Tensor, tuple[int, int]]:
    """(C, T, F, F // 2 + 1) rfft2 of the F x F tiles of the grid (zero outside), tile (i, j) starting at
    (i, j) * (F - side + 1) - side // 2, and the (rows, cols) layout."""
    c, h, w = grid.shape
    valid, r = tile - side + 1, side // 2
    layout = (math.ceil(h / valid), math.ceil(w / valid))
    padded = torch.zeros(c, layout[0] * valid + side - 1, layout[1] * valid + side - 1)
    padded[:, r : r + h, r : r + w] = grid
    tiles = padded.unfold(1, tile, valid).unfold(2, tile, valid)  # (C, rows, cols, F, F)
    return torch.fft.rfft2(tiles.reshape(c, -1, tile, tile)), layout


def build_coarse_map(primitives: PrimitiveBatch, bounds_xy: torch.Tensor, cfg: CoarseSearchConfig) -> CoarseMap:
    """Rasterise, blur and transform the aerial map's primitives (P patches, `bounds_xy` (P, 4))."""
    bounds = torch.as_tensor(bounds_xy, dtype=torch.float64)
    centres = _class_centres(primitives, cfg.classes, cfg.seed)
    grid, origin = _map_grid(primitives, bounds, centres, cfg)
    _, h, w = grid.shape
    n_channels = len(grid)
    side = 2 * _radius_cells(cfg) + 1
    fft_shape = (_fast_size(h + side - 1), _fast_size(w + side - 1))
    cell_patch = _cell_owners(origin, cfg.cell_m, (h, w), bounds)
    # Window energy in float64: it cancels sum(a^2) - sum(a)^2 / n, which float32 FFTs cannot.
    r = _radius_cells(cfg)
    disk = torch.fft.rfft2(_disk(cfg).double(), s=fft_shape)
    window = lambda x: torch.fft.irfft2(torch.fft.rfft2(x.double(), s=fft_shape) * disk, s=fft_shape)[  # noqa: E731
        r : r + h, r : r + w
    ]
    n_window = n_channels * float(_disk(cfg).sum())
    energy = (window(grid.square().sum(0)) - window(grid.sum(0)).square() / n_window).clamp_min(0)
    tile = _tile_size((h, w), side, n_channels)
    tile_spectra, layout = _tile_spectra(grid, side, tile)
    return CoarseMap(
        origin_xy=origin,
        cell_m=cfg.cell_m,
        shape=(h, w),
        tile_size=tile,
        tile_spectra=tile_spectra,
        tile_layout=layout,
        window_energy=energy.float(),
        cell_patch=cell_patch,
        class_centres=centres,
        n_patches=len(bounds),
    )


def _yaws(cfg: CoarseSearchConfig) -> torch.Tensor:
    return torch.arange(cfg.yaws, dtype=torch.float32) * (2 * math.pi / cfg.yaws)


def submap_scores(cmap: CoarseMap, ground: PrimitiveSet, centre_odom_xy: torch.Tensor,
                  cfg: CoarseSearchConfig, *, out: torch.Tensor | None = None) -> torch.Tensor:
    """(yaws, H, W) Pearson correlation of the submap (odom frame, centred at `centre_odom_xy`)
    rotated by each yaw and centred on each cell, with the map inside the submap's disk.

    A submap without primitives scores 0 everywhere, and so do cells whose window holds less
    than `min_window_energy` (empty or nearly empty map). `out`: a (yaws, H, W) float32 tensor to
    write the volume into (a caller scoring submap after submap reuses one; fresh volumes of this
    size cost as much in page faults as the FFTs).
    """
    r = _radius_cells(cfg)
    side = 2 * r + 1
    xy, cls, angle = _primitive_points(
        ground.points_xy, ground.point_descriptors, ground.line_endpoints, ground.line_descriptors,
        cmap.class_centres, cfg.cell_m / 2,
    )
    xy = xy - centre_odom_xy.float()
    yaws = _yaws(cfg)
    rotation = rotation_matrix(yaws)  # (K, 2, 2)
    rotated = torch.einsum("kij,nj->kni", rotation, xy)
    half = (r + 0.5) * cfg.cell_m
    disk = _disk(cfg)
    n_classes = _n_channels(len(cmap.class_centres), cfg)
    channels = _channels(cls, angle + yaws[:, None], cfg)  # (K, M): line angles turn with the yaw
    kernel = _blur(_rasterise(rotated, channels, (-half, -half), cfg.cell_m, (side, side), n_classes), cfg.blur_cells)
    kernel = kernel * disk
    n_window = n_classes * disk.sum()
    kernel = (kernel - kernel.sum((1, 2, 3), keepdim=True) / n_window) * disk  # zero mean inside the disk
    kernel_norm = kernel.flatten(1).norm(dim=1)  # (K,)
    h, w = cmap.shape
    tile = cmap.tile_size
    valid = tile - side + 1
    rows, cols = cmap.tile_layout
    volume = torch.empty(len(yaws), h, w) if out is None else out
    # Overlap-save: each F x F map tile's circular correlation with the kernel is exact on its last
    # F - side + 1 rows and columns. The kernel's spectrum is then F x F, not the padded map's: at
    # the map's size its column FFTs were most of a submap's time. One yaw at a time through buffers
    # made once per call (fresh volumes of this size cost as much in page faults as the FFTs).
    summed = torch.empty(cmap.tile_spectra.shape[1:], dtype=cmap.tile_spectra.dtype)
    product = torch.empty_like(summed)
    corr = torch.empty(rows * cols, tile, tile)
    tiled = torch.empty(rows * valid, cols * valid)  # the tiles' exact cells side by side
    energy_sqrt = cmap.window_energy.sqrt()
    ok_cells = cmap.window_energy >= cfg.min_window_energy
    flipped = torch.flip(kernel, (-2, -1))
    for y in range(len(yaws)):
        if kernel_norm[y] == 0:
            volume[y].zero_()
            continue
        # correlation = convolution with the flipped kernel
        # rfft2(s=(F, F)) in two passes, the first over the kernel's few rows only (the others are zero)
        spectra = torch.fft.fft(torch.fft.rfft(flipped[y], n=tile, dim=-1), n=tile, dim=-2)  # (C, F, F // 2 + 1)
        torch.mul(cmap.tile_spectra[0], spectra[0], out=summed)
        for c in range(1, n_classes):
            summed.add_(torch.mul(cmap.tile_spectra[c], spectra[c], out=product))
        torch.fft.irfft2(summed, s=(tile, tile), out=corr)
        tiled.view(rows, valid, cols, valid).copy_(
            corr[:, side - 1 :, side - 1 :].reshape(rows, cols, valid, valid).transpose(1, 2))
        # Pearson: divided by both norms where the map has energy
        torch.div(tiled[:h, :w], torch.where(ok_cells, kernel_norm[y] * energy_sqrt, 1.0), out=volume[y])
        volume[y].masked_fill_(~ok_cells, 0.0)
    return volume


def chain_scores(previous: torch.Tensor | None, scores: torch.Tensor, step_odom_xy: torch.Tensor,
                 cmap: CoarseMap, cfg: CoarseSearchConfig, *, out: torch.Tensor | None = None) -> torch.Tensor:
    """The chain volume (yaws, H, W) after one more submap: `scores` plus the decayed previous chain,
    max-pooled over the drift slack (cells and neighbouring yaws) and moved by the odometry step
    from the previous submap centre (`step_odom_xy`, odom frame) rotated by each yaw.

    `out`: a (yaws, H, W) tensor to write the chain into; it may be `previous` (updated in place)
    or `scores`. Without it the result is new, or `scores` itself when there is nothing to add.
    """
    if previous is None or cfg.chain_decay == 0:
        return scores if out is None else out.copy_(scores)
    yaws = _yaws(cfg)
    step = step_odom_xy.float()
    shift_x = torch.cos(yaws) * step[0] - torch.sin(yaws) * step[1]
    shift_y = torch.sin(yaws) * step[0] + torch.cos(yaws) * step[1]
    h, w = cmap.shape
    # grid_sample reads the previous volume at cell - shift, in normalised [-1, 1] coordinates.
    theta = torch.zeros(len(yaws), 2, 3)
    theta[:, 0, 0] = theta[:, 1, 1] = 1.0
    theta[:, 0, 2] = -shift_x / cfg.cell_m * 2 / w
    theta[:, 1, 2] = -shift_y / cfg.cell_m * 2 / h
    sources = [_shift_sources(theta[y : y + 1], h, w) for y in range(len(yaws))]
    rows = torch.stack([r for r, _ in sources]).numpy()
    cols = torch.stack([c for _, c in sources]).numpy()
    result = torch.empty_like(scores) if out is None else out
    for name, t in (("previous", previous), ("scores", scores), ("out", result)):
        if t.device.type != "cpu" or t.dtype != torch.float32 or not t.is_contiguous() or t.shape != scores.shape:
            raise ValueError(f"chain_scores: {name} must be a contiguous CPU float32 tensor of shape "
                             f"{tuple(scores.shape)}, got {t.dtype} {tuple(t.shape)} on {t.device}")
    prev, new, res = previous.numpy(), scores.numpy(), result.numpy()
    # yaw ranges side by side; each reads copies of its neighbours' boundary planes, which they overwrite
    ranges = [(a, b, prev[(a - 1) % len(yaws)].copy(), prev[b % len(yaws)].copy()) for a, b in _thread_ranges(len(yaws))]
    slack = int(math.ceil(cfg.chain_slack_m / cfg.cell_m))
    thread_map(lambda r: chain_yaws(prev, new, rows, cols, slack, cfg.chain_decay, r[0], r[1], r[2], r[3], res),
               ranges)
    return result


def _thread_ranges(n: int) -> list[tuple[int, int]]:
    """0..n split into one contiguous range per pool thread (at most n ranges), for the compiled passes."""
    bounds = np.linspace(0, n, min(cpu_threads(), max(n, 1)) + 1).astype(int)
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _shift_sources(theta: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Source row (H,) and column (W,) of each output cell of
    grid_sample(mode="nearest", padding_mode="zeros", align_corners=False) on the affine_grid of the
    translation `theta` (1, 2, 3), -1 where it falls off the grid. A translation's grid is
    separable, so grid_sample itself runs on index ramps along one axis: the rounding is its own,
    at the cost of H + W samples instead of H W."""
    grid_x = torch.nn.functional.affine_grid(theta, [1, 1, 1, w], align_corners=False)
    grid_x[..., 1] = 0.0  # the ramp's one row
    ramp_x = torch.arange(1, w + 1, dtype=torch.float32).view(1, 1, 1, w)
    cols = torch.nn.functional.grid_sample(ramp_x, grid_x, mode="nearest", padding_mode="zeros", align_corners=False)
    grid_y = torch.nn.functional.affine_grid(theta, [1, 1, h, 1], align_corners=False)
    grid_y[..., 0] = 0.0
    ramp_y = torch.arange(1, h + 1, dtype=torch.float32).view(1, 1, h, 1)
    rows = torch.nn.functional.grid_sample(ramp_y, grid_y, mode="nearest", padding_mode="zeros", align_corners=False)
    return rows.view(h).long() - 1, cols.view(w).long() - 1


def patch_priors(cmap: CoarseMap, volume: torch.Tensor, cfg: CoarseSearchConfig) -> CoarsePriors:
    """Best score of each patch over its cells and all yaws, with the yaw and centre where it is."""
    # amax / argmax over the yaws in one compiled pass (torch's argmax along the outer axis is
    # slow), the cells split over the threads
    flat = volume.detach().cpu().contiguous().view(len(volume), -1).numpy()
    best_np, best_yaw_np = np.empty(flat.shape[1], flat.dtype), np.empty(flat.shape[1], np.int64)
    thread_map(lambda r: best_yaws(flat, r[0], r[1], best_np, best_yaw_np), _thread_ranges(flat.shape[1]))
    best, best_yaw = torch.from_numpy(best_np), torch.from_numpy(best_yaw_np)
    on_map = cmap.cell_patch >= 0
    owner = cmap.cell_patch.clamp_min(0)
    value = torch.where(on_map, best, float("-inf"))
    score = torch.full((cmap.n_patches,), float("-inf")).scatter_reduce(0, owner, value, "amax")
    # first cell reaching its patch's best score (deterministic tie-break)
    cell = torch.arange(len(value))
    winner = on_map & (value == score[owner])
    first = torch.full((cmap.n_patches,), len(value)).scatter_reduce(
        0, owner, torch.where(winner, cell, len(value)), "amin"
    ).clamp_max(len(value) - 1)
    w = cmap.shape[1]
    row, col = first // w, first % w
    centre = torch.stack([
        cmap.origin_xy[0] + (col.double() + 0.5) * cmap.cell_m,
        cmap.origin_xy[1] + (row.double() + 0.5) * cmap.cell_m,
    ], -1)
    return CoarsePriors(score=score, yaw=_yaws(cfg)[best_yaw[first]], centre_xy=centre)


class CoarseSearch:
    """The coarse search over one map for a robot's successive submaps (holds the chain volume)."""

    def __init__(self, primitives: PrimitiveBatch, bounds_xy: torch.Tensor, cfg: CoarseSearchConfig) -> None:
        self.cfg = cfg
        self.map = build_coarse_map(primitives, bounds_xy, cfg)
        # the volumes live in two buffers for the whole drive (fresh ones cost page faults)
        self._single = torch.empty(cfg.yaws, *self.map.shape)
        self._chain: torch.Tensor | None = None
        self._previous_centre: torch.Tensor | None = None

    def add_submap(self, ground: PrimitiveSet, centre_odom_xy: torch.Tensor) -> CoarsePriors:
        """Score the next submap (odom frame, centred at `centre_odom_xy`) chained with the earlier ones."""
        centre = torch.as_tensor(centre_odom_xy, dtype=torch.float64).cpu()
        single = submap_scores(self.map, ground.to(device="cpu"), centre, self.cfg, out=self._single)
        step = centre - self._previous_centre if self._previous_centre is not None else torch.zeros(2)
        chain = torch.empty_like(single) if self._chain is None else self._chain
        self._chain = chain_scores(self._chain, single, step, self.map, self.cfg, out=chain)
        self._previous_centre = centre
        return patch_priors(self.map, self._chain, self.cfg)
