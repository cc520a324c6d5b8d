"""Tests of the batched CLIPPER solver: the reference's golden 4/3-point scene, planted cliques,
batching with padding, seeding, roundings (including the weighted clique where CLIPPER's
default rounding loses recall) and the clique guarantee."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from meridian_torch.config.matching import ClipperConfig
from meridian_torch.matching.clipper import ClipperResult, inlier_indices, solve_clipper
from meridian_torch.matching.clipper.rounding import _densest_exact

ROUNDINGS = ("clipper", "support", "densest")
DTYPES = (torch.float32, torch.float64)


pytestmark = pytest.mark.usefixtures("single_thread")


def _euclidean_affinity(
    model: torch.Tensor, data: torch.Tensor, sigma: float = 0.01, eps: float = 0.06
) -> torch.Tensor:
    """CLIPPER's EuclideanDistance invariant over all-to-all associations k = i * len(data) + j."""
    assoc = torch.tensor(list(itertools.product(range(len(model)), range(len(data)))))
    a, b = model[assoc[:, 0]], data[assoc[:, 1]]
    c = (torch.cdist(a, a) - torch.cdist(b, b)).abs()
    M = torch.where(c < eps, torch.exp(-(c**2) / (2 * sigma**2)), torch.zeros_like(c))
    # Associations sharing an endpoint are inconsistent (distinctness).
    shared = (assoc[:, None, 0] == assoc[None, :, 0]) | (assoc[:, None, 1] == assoc[None, :, 1])
    M = torch.where(shared, torch.zeros_like(M), M)
    return M.fill_diagonal_(1.0)


def _golden_scene() -> torch.Tensor:
    """clipper test/affinity_test.cpp: 4 model points, the data are 3 of them moved rigidly."""
    model = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 3, 0], [2, 2, 0]], dtype=torch.float64)
    angle = math.pi / 8
    c, s = math.cos(angle), math.sin(angle)
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    t = torch.tensor([5.0, 3.0, 0.0], dtype=torch.float64)
    data = (model - t) @ R  # T_MD^-1 applied to the model points: R^T (p - t)
    return _euclidean_affinity(model, data[:3])


# The expected affinity of the reference test ("from MATLAB"), binary for perfect data.
_GOLDEN_M = torch.tensor(
    [
        [1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0],
        [0, 1, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0],
        [0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0],
        [0, 1, 0, 1, 0, 0, 0, 0, 0, 0, 1, 0],
        [1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 0, 0],
        [0, 0, 0, 0, 0, 1, 0, 1, 0, 0, 0, 0],
        [0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 1, 0, 1, 0, 0, 0, 0],
        [1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0],
        [0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0],
        [0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 1, 0],
        [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1],
    ],
    dtype=torch.float64,
)


def planted_clique(
    n: int,
    k: int,
    seed: int,
    *,
    p: float = 0.08,
    lo: float = 1.0,
    hi: float = 1.0,
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random sparse weighted graph (edge probability p, weights U(0, 1)) with a k-clique of
    affinities U(lo, hi) planted on random vertices. Returns (M (n, n), truth (n,) bool)."""
    g = torch.Generator().manual_seed(seed)
    W = torch.rand(n, n, generator=g, dtype=dtype) * (torch.rand(n, n, generator=g) < p)
    members = torch.randperm(n, generator=g)[:k]
    W[members[:, None], members[None, :]] = lo + (hi - lo) * torch.rand(k, k, generator=g, dtype=dtype)
    M = torch.triu(W, 1)
    M = M + M.T
    M.fill_diagonal_(1.0)
    truth = torch.zeros(n, dtype=torch.bool)
    truth[members] = True
    return M, truth


def assert_cliques(result: ClipperResult, M: torch.Tensor, C: torch.Tensor | None = None) -> None:
    """No selected pair is forbidden (C = 0, default C = M > 0) and no padding is selected."""
    allowed = (M > 0) if C is None else (C != 0)
    if allowed.dim() == 2:
        allowed = allowed.unsqueeze(0)
    x = result.inliers
    forbidden = x[:, :, None] & x[:, None, :] & ~allowed
    forbidden &= ~torch.eye(x.shape[-1], dtype=torch.bool)
    assert not bool(forbidden.any())


class TestSolveClipper:
    def test_smoke(self) -> None:
        M, truth = planted_clique(60, 10, 0)
        res = solve_clipper(M)
        assert isinstance(res, ClipperResult)
        assert res.inliers.shape == (1, 60) and res.inliers.dtype == torch.bool
        assert res.u.shape == (1, 60) and res.u.dtype == torch.float64
        assert res.score.shape == res.objective.shape == res.iterations.shape == (1,)
        assert bool(res.converged.all())
        norm = torch.linalg.vector_norm(res.u, dim=-1)
        torch.testing.assert_close(norm, torch.ones(1, dtype=torch.float64))
        assert bool((res.u >= 0).all())
        assert torch.equal(inlier_indices(res, 0), torch.nonzero(truth).flatten())
        # A k-clique of unit affinities has weighted density k.
        torch.testing.assert_close(res.score, torch.tensor([10.0], dtype=torch.float64))

    @pytest.mark.parametrize("batch_size", [1, 2, 5])
    def test_cardinality(self, batch_size: int) -> None:
        Ms, truths = zip(*(planted_clique(50, 8, s) for s in range(batch_size)))
        res = solve_clipper(torch.stack(Ms))
        for field in (res.inliers, res.u):
            assert field.shape == (batch_size, 50)
        for field in (res.score, res.objective, res.iterations, res.penalty_updates, res.converged):
            assert field.shape == (batch_size,)
        assert torch.equal(res.inliers, torch.stack(truths))

    @pytest.mark.parametrize("rounding", ROUNDINGS)
    def test_golden_four_three_points(self, rounding: str) -> None:
        M = _golden_scene()
        assert M.shape == (12, 12)
        torch.testing.assert_close(M, _GOLDEN_M, rtol=0.0, atol=1e-12)
        res = solve_clipper(M, cfg=ClipperConfig(rounding=rounding))
        # Inliers are the identity associations (0,0), (1,1), (2,2): k = 0, 4, 8.
        assert inlier_indices(res).tolist() == [0, 4, 8]
        torch.testing.assert_close(res.score, torch.tensor([3.0], dtype=torch.float64))

    @pytest.mark.parametrize("rounding", ROUNDINGS)
    @pytest.mark.parametrize(("n", "seed"), [(60, 0), (60, 1), (120, 2), (120, 3), (200, 4), (200, 5)])
    def test_planted_clique_recovered(self, n: int, seed: int, rounding: str) -> None:
        M, truth = planted_clique(n, 12, seed)
        res = solve_clipper(M, cfg=ClipperConfig(rounding=rounding))
        assert torch.equal(res.inliers[0], truth)  # precision and recall 1

    @pytest.mark.parametrize("dtype", DTYPES)
    def test_dtype_follows_input(self, dtype: torch.dtype) -> None:
        M, truth = planted_clique(120, 15, 7, lo=0.8, dtype=dtype)
        res = solve_clipper(M, cfg=ClipperConfig(rounding="support"))
        assert res.u.dtype == res.score.dtype == res.objective.dtype == dtype
        assert torch.equal(res.inliers[0], truth)

    def test_weighted_clique_default_rounding_loses_recall(self) -> None:
        # clipper.md section 3: a 20-clique with affinities U(0.3, 1) has F ~ 1 + 19 * 0.65, so
        # round(F) keeps ~13 members; the support and the exact densest subgraph keep all 20.
        M, truth = planted_clique(150, 20, 11, lo=0.3, hi=1.0)
        results = {r: solve_clipper(M, cfg=ClipperConfig(rounding=r)) for r in ROUNDINGS}
        heuristic = results["clipper"].inliers[0]
        assert bool((heuristic <= truth).all())  # precision 1
        assert int(heuristic.sum()) == round(float(results["clipper"].objective[0])) < 20
        for r in ("support", "densest"):
            assert torch.equal(results[r].inliers[0], truth)
        assert float(results["densest"].score[0]) > float(results["clipper"].score[0])

    def test_batched_matches_loop(self) -> None:
        sizes = (60, 90, 130)
        n_max = max(sizes)
        g = torch.Generator().manual_seed(3)
        problems = [planted_clique(n, 10, 20 + i, lo=0.6) for i, n in enumerate(sizes)]
        starts = [torch.rand(n, generator=g, dtype=torch.float64) for n in sizes]
        M = torch.zeros(len(sizes), n_max, n_max, dtype=torch.float64)
        u0 = torch.zeros(len(sizes), n_max, dtype=torch.float64)
        valid = torch.zeros(len(sizes), n_max, dtype=torch.bool)
        for b, ((Mb, _), n) in enumerate(zip(problems, sizes)):
            M[b, :n, :n] = Mb
            # Padding carries garbage affinities and start values: they must be ignored.
            M[b, n:, :] = 1.0
            M[b, :, n:] = 1.0
            u0[b, :n] = starts[b]
            u0[b, n:] = 5.0
            valid[b, :n] = True
        for rounding in ROUNDINGS:
            cfg = ClipperConfig(rounding=rounding)
            batched = solve_clipper(M, valid=valid, u0=u0, cfg=cfg)
            assert not bool((batched.inliers & ~valid).any())
            assert bool((batched.u[~valid] == 0).all())
            for b, ((Mb, truth), n) in enumerate(zip(problems, sizes)):
                single = solve_clipper(Mb, u0=starts[b], cfg=cfg)
                assert torch.equal(batched.inliers[b, :n], single.inliers[0])
                torch.testing.assert_close(batched.u[b, :n], single.u[0], rtol=1e-6, atol=1e-6)
                torch.testing.assert_close(batched.score[b], single.score[0])
                if rounding != "clipper":
                    assert torch.equal(single.inliers[0], truth)

    def test_seeded_runs_identical(self) -> None:
        M, _ = planted_clique(100, 10, 9, lo=0.5)
        M = torch.stack([M, M.flip(0, 1)])
        runs = [solve_clipper(M, generator=torch.Generator().manual_seed(42)) for _ in range(2)]
        runs += [solve_clipper(M) for _ in range(2)]  # default: a generator seeded with cfg.seed
        for a, b in [(runs[0], runs[1]), (runs[2], runs[3])]:
            for field in ("inliers", "u", "score", "objective", "iterations", "penalty_updates"):
                assert torch.equal(getattr(a, field), getattr(b, field))
        other = solve_clipper(M, generator=torch.Generator().manual_seed(43))
        assert not torch.equal(other.u, runs[0].u)  # the seed does matter

    def test_u0_respected(self) -> None:
        # Two disjoint 6-cliques of unit affinity: the start vector decides which one is found.
        n = 30
        M = torch.eye(n, dtype=torch.float64)
        first, second = torch.arange(0, 6), torch.arange(10, 16)
        for clique in (first, second):
            M[clique[:, None], clique[None, :]] = 1.0
        for clique in (first, second):
            u0 = torch.full((n,), 0.01, dtype=torch.float64)
            u0[clique] = 1.0
            assert torch.equal(inlier_indices(solve_clipper(M, u0=u0)), clique)
        # A start on a single vertex stays in that vertex's component.
        u0 = torch.zeros(n, dtype=torch.float64)
        u0[12] = 1.0
        assert torch.equal(inlier_indices(solve_clipper(M, u0=u0)), second)
        # One (n,) start vector serves every problem of a batch.
        batched = solve_clipper(torch.stack([M, M.flip(0, 1)]), u0=u0)
        assert torch.equal(inlier_indices(batched, 0), second)
        assert torch.equal(inlier_indices(batched, 1), solve_clipper(M.flip(0, 1), u0=u0).inliers[0].nonzero().flatten())

    @pytest.mark.parametrize("rounding", ROUNDINGS)
    def test_returned_sets_are_cliques(self, rounding: str) -> None:
        g = torch.Generator().manual_seed(5)
        n, B = 30, 3
        W = torch.rand(B, n, n, generator=g, dtype=torch.float64) * (torch.rand(B, n, n, generator=g) < 0.3)
        M = torch.triu(W, 1)
        M = M + M.mT
        # An explicit constraint matrix stricter than M's pattern: forbidden pairs keep their
        # affinity, so only the penalty removes them.
        extra = torch.rand(B, n, n, generator=g) < 0.5
        extra = torch.triu(extra, 1)
        C = (M > 0) & ~(extra | extra.mT)
        # One outer iteration leaves forbidden pairs in the support: the repair must remove them.
        for outer in (1000, 1):
            cfg = ClipperConfig(rounding=rounding, max_outer_iterations=outer)
            assert_cliques(solve_clipper(M, C, cfg=cfg), M, C)
            assert_cliques(solve_clipper(M, cfg=cfg), M)

    def test_unconstrained_selects_everything(self) -> None:
        # clipper.md section 7: with an all-ones C the support is everything.
        M = torch.full((2, 8, 8), 0.5, dtype=torch.float64)
        C = torch.ones(8, 8, dtype=torch.bool).expand(2, 8, 8)
        res = solve_clipper(M, C, cfg=ClipperConfig(rounding="support"))
        assert bool(res.inliers.all())
        assert bool((res.penalty_updates == 0).all())

    def test_diagonal_modes(self) -> None:
        M, truth = planted_clique(60, 8, 2)
        M0 = M.clone().fill_diagonal_(0.0)
        # CLIPPER ignores the diagonal it is given.
        a, b = solve_clipper(M), solve_clipper(M0)
        torch.testing.assert_close(a.u, b.u)
        assert torch.equal(a.inliers, b.inliers)
        # Unary weights: a strong single vertex outweighs a tiny clique.
        U = torch.eye(4, dtype=torch.float64) * torch.tensor([5.0, 1.0, 1.0, 1.0])
        U[1, 2] = U[2, 1] = 1.0
        res = solve_clipper(U, cfg=ClipperConfig(diagonal="input", rounding="densest"))
        assert inlier_indices(res).tolist() == [0]
        torch.testing.assert_close(res.score, torch.tensor([5.0], dtype=torch.float64))

    def test_empty(self) -> None:
        for M in (torch.zeros(0, 0), torch.zeros(3, 0, 0), torch.zeros(0, 5, 5)):
            res = solve_clipper(M)
            assert res.inliers.shape == res.u.shape == (M.shape[0] if M.dim() == 3 else 1, M.shape[-1])
            assert not bool(res.inliers.any())
        # An all-invalid problem next to a real one; and an edgeless problem (singletons only).
        Mb, truth = planted_clique(40, 8, 1)
        M = torch.stack([Mb, Mb, torch.eye(40, dtype=torch.float64)])
        valid = torch.ones(3, 40, dtype=torch.bool)
        valid[1] = False
        for rounding in ROUNDINGS:
            res = solve_clipper(M, valid=valid, cfg=ClipperConfig(rounding=rounding))
            assert torch.equal(res.inliers[0], truth)
            assert not bool(res.inliers[1].any()) and float(res.score[1]) == 0.0
            assert int(res.inliers[2].sum()) <= 1
            assert_cliques(res, M)

    def test_exception(self) -> None:
        M, _ = planted_clique(10, 3, 0)
        with pytest.raises(ValueError, match="floating"):
            solve_clipper(M.to(torch.int64))
        with pytest.raises(ValueError, match="shape"):
            solve_clipper(M[:, :9])
        with pytest.raises(ValueError, match="C must have"):
            solve_clipper(M, torch.ones(9, 9, dtype=torch.bool))
        with pytest.raises(ValueError, match="valid"):
            solve_clipper(M, valid=torch.ones(9, dtype=torch.bool))
        with pytest.raises(ValueError, match="valid"):
            solve_clipper(M, valid=torch.ones(10, dtype=torch.int64))
        with pytest.raises(ValueError, match="u0"):
            solve_clipper(M, u0=-torch.ones(10, dtype=torch.float64))
        with pytest.raises(ValueError, match="symmetric"):
            asym = M.clone()
            asym[0, 5] += 0.5
            solve_clipper(asym)
        with pytest.raises(ValueError, match="nonnegative"):
            solve_clipper(M - 2.0)
        with pytest.raises(ValidationError):
            ClipperConfig(rounding="nonzero")
        with pytest.raises(ValidationError):
            ClipperConfig(unknown_key=1)  # type: ignore[call-arg]


@pytest.mark.parametrize("seed", range(8))
def test_densest_exact_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s = 9
    W = np.triu(rng.random((s, s)) * (rng.random((s, s)) < 0.6), 1)
    W = W + W.T
    np.fill_diagonal(W, rng.random(s) if seed % 2 else 1.0)
    best = max(
        (x @ W @ x / x.sum(), x.sum())
        for bits in itertools.product((0.0, 1.0), repeat=s)
        if (x := np.array(bits)).sum() > 0
    )[0]
    keep = _densest_exact(W)
    x = np.zeros(s)
    x[keep] = 1.0
    assert x @ W @ x / x.sum() == pytest.approx(best, rel=1e-9)


def test_numpy_inputs_equal_torch_inputs() -> None:
    M, _ = planted_clique(30, 6, 4)
    u0 = torch.rand(30, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    C = (M > 0).to(torch.int64)
    from_torch = solve_clipper(M, C, u0=u0)
    from_numpy = solve_clipper(M.numpy(), C.numpy(), u0=u0.numpy(), valid=np.ones(30, dtype=bool))
    assert torch.equal(from_torch.inliers, from_numpy.inliers)
    torch.testing.assert_close(from_torch.u, from_numpy.u)
    with pytest.raises(ValueError, match="M"):
        solve_clipper(np.array([["a", "b"], ["c", "d"]]))


def test_dense_problem_never_collapses_to_the_empty_set() -> None:
    # A 42-association loop-closure graph from the demo world (86 % of pairs consistent) on which
    # the default data-driven initial penalty once made a full step clamp u to zero, and the zero
    # vector (F = 0) was accepted because it beat the heavily penalised negative objective.
    M = torch.from_numpy(np.load(Path(__file__).parent / "data" / "clipper_dense_collapse.npy"))
    result = solve_clipper(M, generator=torch.Generator().manual_seed(0))
    chosen = torch.nonzero(result.inliers[0]).flatten()
    assert len(chosen) >= 3
    assert bool((M[chosen][:, chosen] > 0).all())  # a clique of the consistency graph
    gentle = solve_clipper(M, generator=torch.Generator().manual_seed(0), cfg=ClipperConfig(initial_d=0.5))
    assert float(result.score[0]) >= 0.99 * float(gentle.score[0])


@pytest.mark.parametrize("rounding", ["clipper", "support", "densest"])
@pytest.mark.parametrize("seed", range(4))
def test_sparse_solve_equals_the_dense_solve(seed: int, rounding: str) -> None:
    """The edge-list solver takes the dense solver's steps: same inliers, iterations and penalty
    updates, the same u and score up to summation order."""
    from meridian_torch.matching.clipper import solve_clipper_sparse

    n = [60, 150, 300, 500][seed]
    M, truth = planted_clique(n, 8 + seed, seed, p=0.03)  # a clique of unit affinities
    cfg = ClipperConfig(rounding=rounding)
    dense = solve_clipper(M, generator=torch.Generator().manual_seed(seed), cfg=cfg)
    i, j = torch.nonzero(torch.triu(M, 1) > 0, as_tuple=True)
    sparse = solve_clipper_sparse(n, (i, j, M[i, j]), generator=torch.Generator().manual_seed(seed), cfg=cfg)
    assert torch.equal(sparse.inliers, dense.inliers)
    assert torch.equal(sparse.iterations, dense.iterations) and torch.equal(sparse.penalty_updates, dense.penalty_updates)
    torch.testing.assert_close(sparse.u, dense.u, rtol=0, atol=1e-10)
    torch.testing.assert_close(sparse.score, dense.score, rtol=1e-12, atol=0)
    assert bool(sparse.inliers[0][truth].all())  # and it finds the planted clique
    assert_cliques(sparse, M)


def test_sparse_solve_of_a_graph_without_edges_and_bad_edges() -> None:
    from meridian_torch.matching.clipper import solve_clipper_sparse

    empty = (torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64))
    result = solve_clipper_sparse(5, empty, generator=torch.Generator().manual_seed(0))
    dense = solve_clipper(torch.eye(5, dtype=torch.float64), generator=torch.Generator().manual_seed(0))
    assert torch.equal(result.inliers, dense.inliers) and int(result.inliers.sum()) == 1
    with pytest.raises(ValueError, match="i < j < n"):
        solve_clipper_sparse(3, (torch.tensor([2]), torch.tensor([1]), torch.tensor([0.5], dtype=torch.float64)))
    with pytest.raises(ValueError, match="finite and positive"):
        solve_clipper_sparse(3, (torch.tensor([0]), torch.tensor([1]), torch.tensor([-0.5], dtype=torch.float64)))
    with pytest.raises(ValueError, match="repeat"):
        solve_clipper_sparse(3, (torch.tensor([0, 0]), torch.tensor([1, 1]), torch.tensor([0.5, 0.5], dtype=torch.float64)))


@given(n=st.integers(1, 12), density=st.floats(0.0, 1.0), seed=st.integers(0, 1000))
@settings(max_examples=60, deadline=None)
def test_sparse_solve_equals_dense_on_any_graph(n: int, density: float, seed: int) -> None:
    # the symmetric CSR is built by hand (sorted keys, int32 indices): isolated vertices anywhere,
    # including trailing rows without edges, must give the dense solve's steps
    from meridian_torch.matching.clipper import solve_clipper_sparse

    g = torch.Generator().manual_seed(seed)
    M = torch.rand(n, n, generator=g, dtype=torch.float64)
    M = torch.where(torch.rand(n, n, generator=g) < density, M, torch.zeros_like(M))
    M = torch.triu(M, 1)
    M = M + M.T
    M.fill_diagonal_(1.0)
    i, j = torch.nonzero(torch.triu(M, 1), as_tuple=True)
    order = torch.randperm(len(i), generator=g)  # edges in any order
    sparse = solve_clipper_sparse(n, (i[order], j[order], M[i, j][order]), generator=torch.Generator().manual_seed(seed))
    dense = solve_clipper(M, generator=torch.Generator().manual_seed(seed))
    assert torch.equal(sparse.inliers, dense.inliers)
    torch.testing.assert_close(sparse.u, dense.u, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", range(6))
def test_sparse_problem_scipy_products_equal_torch_csr_bitwise(seed: int) -> None:
    from meridian_torch.matching.clipper.ascent import _SparseProblem
    from meridian_torch.matching.clipper.sparse import _symmetric_csr

    g = torch.Generator().manual_seed(seed)
    n = [1, 7, 300, 2500, 40, 900][seed]
    m = int(torch.randint(0, 40 * n, (1,), generator=g))
    i, j = torch.randint(0, n, (2, m), generator=g)
    key = torch.unique(torch.minimum(i, j) * n + torch.maximum(i, j))
    key = key[key // n != key % n]
    M_off, pattern = _symmetric_csr(n, key // n, key % n, torch.rand(len(key), dtype=torch.float64, generator=g))
    diag, d = torch.ones(1, n, dtype=torch.float64), torch.rand(1, dtype=torch.float64, generator=g)
    fast = _SparseProblem(M_off, pattern, diag, d)
    plain = _SparseProblem(M_off, pattern, diag, d)
    plain._scipy = None  # torch's CSR products
    assert fast._scipy is not None
    for u in (torch.rand(1, n, dtype=torch.float64, generator=g), torch.zeros(1, n, dtype=torch.float64),
              torch.randn(1, n, dtype=torch.float64, generator=g) * 1e3):
        assert torch.equal(fast.mv(u), plain.mv(u))
        assert torch.equal(fast.cb_mv(u), plain.cb_mv(u))
    float32 = _SparseProblem(M_off.to(torch.float32), pattern.to(torch.float32), diag.float(), d.float())
    assert float32._scipy is None  # other dtypes (and devices) keep torch's products


def _sparse_case(case: str) -> tuple[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor], ClipperConfig]:
    """(n, edges, cfg) of the problems the compiled sparse solve is checked on."""
    if case == "edgeless":
        return 7, (torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64),
                   torch.zeros(0, dtype=torch.float64)), ClipperConfig()
    if case == "single":
        return 1, (torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64),
                   torch.zeros(0, dtype=torch.float64)), ClipperConfig()
    if case == "penalty_grows":  # a dense weighted graph from a tiny penalty: d must grow many times
        M, _ = planted_clique(80, 6, 11, p=0.6, lo=0.5, hi=1.0)
        cfg = ClipperConfig(initial_d=1e-4, rounding="densest")
    else:  # a weighted planted clique in noise
        seed = int(case[-1])
        M, _ = planted_clique([40, 200, 700][seed], 5 + 3 * seed, seed, p=0.05 + 0.05 * seed, lo=0.6, hi=1.0)
        cfg = ClipperConfig(rounding=["clipper", "support", "densest"][seed])
    i, j = torch.nonzero(torch.triu(M, 1) > 0, as_tuple=True)
    return M.shape[0], (i, j, M[i, j]), cfg


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.floats(0.0, 1.0), st.floats(0.0, 50.0))
def test_compiled_penalised_product_equals_the_row_by_row_sums(seed: int, n: int, zeros: float, d: float) -> None:
    """The kernel's product scatters from the rows of u's nonzero entries; a plain pass over every
    row (sums in column order, as the kernel did before) gives the same bits, zeros (+-0) in u
    included."""
    from meridian_torch.matching.clipper.kernels import _penalised_mv
    from meridian_torch.matching.clipper.sparse import _symmetric_csr

    rng = np.random.default_rng(seed)
    i, j = np.triu_indices(n, 1)
    keep = rng.random(len(i)) < rng.random()
    M_off, _ = _symmetric_csr(n, torch.from_numpy(i[keep]), torch.from_numpy(j[keep]),
                              torch.from_numpy(rng.uniform(0.01, 1.0, int(keep.sum()))))
    crow, col, value = M_off.crow_indices().numpy(), M_off.col_indices().numpy(), M_off.values().numpy()  # as the solve
    u = rng.random(n) * 10.0 ** rng.integers(-12, 1, n)
    u[rng.random(n) < zeros] = 0.0
    u[rng.random(n) < 0.1] = -0.0
    out, scratch = np.empty(n), np.empty(n)
    F = _penalised_mv(crow, col, value, d, u, out, scratch)
    total = 0.0
    for a in range(n):
        total += u[a]
    expected, F_expected = np.empty(n), 0.0
    for a in range(n):
        mu, pu = 0.0, 0.0
        for k in range(crow[a], crow[a + 1]):
            mu += value[k] * u[col[k]]
            pu += u[col[k]]
        expected[a] = mu + u[a] - d * (total - u[a] - pu)
        F_expected += u[a] * expected[a]
    assert np.array_equal(out.view(np.int64), expected.view(np.int64))  # bits, signs of zeros included
    assert np.float64(F).view(np.int64) == np.float64(F_expected).view(np.int64)


@pytest.mark.parametrize("case", ["noise0", "noise1", "noise2", "penalty_grows", "edgeless", "single"])
def test_compiled_sparse_solve_takes_the_torch_solves_steps(case: str) -> None:
    """The compiled continuous solve (`kernels.sparse_homotopy`) against torch's loop: the same
    steps and inliers, u and the scores up to summation order."""
    from meridian_torch.matching.clipper import solve_clipper_sparse

    n, edges, cfg = _sparse_case(case)
    ref, fast = (solve_clipper_sparse(n, edges, generator=torch.Generator().manual_seed(3), cfg=cfg, compiled=c)
                 for c in (False, True))
    assert torch.equal(fast.inliers, ref.inliers) and bool(fast.inliers.any())
    assert torch.equal(fast.iterations, ref.iterations)
    assert torch.equal(fast.penalty_updates, ref.penalty_updates) and torch.equal(fast.converged, ref.converged)
    torch.testing.assert_close(fast.u, ref.u, rtol=0, atol=1e-10)
    torch.testing.assert_close(fast.objective, ref.objective, rtol=1e-9, atol=0)
    torch.testing.assert_close(fast.score, ref.score, rtol=1e-9, atol=0)
    if case == "penalty_grows":
        assert int(ref.penalty_updates[0]) >= 3
