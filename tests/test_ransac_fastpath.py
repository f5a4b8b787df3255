"""RANSAC's CPU fast path gives what the torch path (and the previous implementation) gives, bit for bit.

* ``ransac(..., fast=True)`` (the CPU default: NumPy edge-length checks, the leaner fit) vs ``fast=False``
  (the torch path of other devices), on several settings and seeds;
* its parts: the NumPy edge check, the leaner fit, the lexsort ``np.unique`` of rows, the grid built with
  few large writes, the batch's best hypotheses' squared distances without their *out* points, squared
  distances asked for only at a tie, a coarser grid for the first hypotheses;
* results recorded with the implementation before the fast path (same seeds, same problems).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pcrcg.geometry import random_rotation
from pcrcg.registration.ransac import (RansacConfig, _Best, _EdgeCheck, _fit_and_check_distance,
                                      _fit_and_check_distance_cpu, _GridOverlapScore, _Hypotheses, _unique_rows,
                                      ransac)
from pcrcg.testing.pairs import correspondence_problem


def _problem(seed: int, n: int, inlier_ratio: float):
    """src (n, 3), tgt (n, 3), corr (n, 2): :func:`correspondence_problem` without its generator."""
    return correspondence_problem(seed, n, inlier_ratio)[1:]


# (seed, N, inlier ratio, settings) -> (iterations, n_checked, n_inliers, translation) of the implementation
# before the fast path (torch edge checks and fit, grid after 16 hypotheses), max_iterations=20000
PREVIOUS = [
    ((0, 1000, 0.3, {}), (312, 15, 280, [0.781821, 1.202406, 1.09188])),
    ((1, 1000, 0.08, {}), (9164, 8, 91, [-0.933494, -0.874863, -0.105176])),
    ((2, 600, 0.05, {"score": "correspondences"}), (20000, 11, 24, [1.414494, -1.264598, 1.537494])),
    ((3, 800, 0.1, {"dtype": "float64"}), (8381, 5, 75, [-1.242422, -0.446647, -1.925416])),
    ((4, 800, 0.15, {"max_validation": 200, "confidence": 1.0}), (20000, 78, 120, [1.337609, -0.982393, 0.212555])),
    ((5, 500, 0.3, {"ransac_n": 4}), (827, 5, 151, [2.430012, 0.228595, 0.379166])),
]


@pytest.mark.parametrize("case,previous", PREVIOUS, ids=[str(c[0][:3]) for c in PREVIOUS])
def test_fast_path_equals_torch_path_and_the_previous_results(case, previous):
    seed, n, ratio, kw = case
    src, tgt, corr = _problem(seed, n, ratio)
    cfg = RansacConfig(max_iterations=20000, **kw)
    fast = ransac(src, tgt, corr, cfg, seed=seed)
    ref = ransac(src, tgt, corr, cfg, seed=seed, fast=False)
    assert np.array_equal(fast.transform, ref.transform)
    assert (fast.fitness, fast.inlier_rmse, fast.n_inliers, fast.iterations, fast.n_checked) == \
        (ref.fitness, ref.inlier_rmse, ref.n_inliers, ref.iterations, ref.n_checked)
    assert (fast.iterations, fast.n_checked, fast.n_inliers) == previous[:3]
    assert np.allclose(fast.transform[:3, 3], previous[3], atol=2e-6)


def test_fast_path_with_a_generator_leaves_it_where_the_torch_path_does():
    src, tgt, corr = _problem(6, 400, 0.2)
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    ra = ransac(src, tgt, corr, RansacConfig(max_iterations=5000), seed=a)
    rb = ransac(src, tgt, corr, RansacConfig(max_iterations=5000), seed=b, fast=False)
    assert np.array_equal(ra.transform, rb.transform) and a.integers(1 << 30) == b.integers(1 << 30)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [3, 4])
def test_numpy_edge_check_passes_the_same_samples(dtype, n):
    rng = np.random.default_rng(n)
    S = torch.as_tensor(rng.normal(size=(500, 3)), dtype=dtype)
    Q = S @ torch.as_tensor(random_rotation(rng), dtype=dtype).T + 0.03 * torch.randn(500, 3, dtype=dtype)
    Q[::3] = torch.as_tensor(rng.normal(size=(167, 3)), dtype=dtype)  # outliers
    idx = rng.integers(0, 500, size=(20000, n))
    idx[:50] = idx[:50, :1]  # one correspondence drawn n times: zero-length edges pass
    fast_idx, fast_pos = _EdgeCheck(S, Q, n, 0.81, use_numpy=True)(idx)
    ref_idx, ref_pos = _EdgeCheck(S, Q, n, 0.81, use_numpy=False)(idx)
    assert 50 < len(ref_pos) < 20000
    assert torch.equal(fast_idx, ref_idx) and torch.equal(fast_pos, ref_pos)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [3, 4])
def test_leaner_fit_is_the_same_bit_for_bit(dtype, n):
    rng = np.random.default_rng(10 + n)
    ps = torch.as_tensor(rng.normal(size=(300, n, 3)), dtype=dtype)
    R = torch.as_tensor(np.stack([random_rotation(rng) for _ in range(300)]), dtype=dtype)
    pq = ps @ R.transpose(1, 2) + 0.02 * torch.randn(300, n, 3, dtype=dtype)
    pq[::2] = torch.as_tensor(rng.normal(size=(150, n, 3)), dtype=dtype)  # reflections and misfits
    ps[:3] = ps[:3, :1]  # degenerate samples
    pq[:3] = pq[:3, :1]
    for a, b in zip(_fit_and_check_distance(ps, pq, 0.05), _fit_and_check_distance_cpu(ps.clone(), pq.clone(), 0.05)):
        assert torch.equal(a, b)


def test_unique_rows_is_np_unique():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(3000, 3))
    a = a[rng.integers(0, 3000, 5000)]  # repeats
    a[:100, 0] = a[100:200, 0]  # equal first coordinates
    u, c = np.unique(a, axis=0, return_counts=True)
    u2, c2 = _unique_rows(a)
    assert np.array_equal(u, u2) and np.array_equal(c, c2)


def _grid_offset_by_offset(grid: _GridOverlapScore) -> np.ndarray:
    """The grid as the previous implementation built it (one write per offset)."""
    c, reach, origin, dims, _ = grid._frame(grid.tree.data, grid.distance)
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    occupied = np.unique(np.floor((grid.tree.data - origin) / c).astype(np.int64) @ strides)
    r = np.arange(-reach, reach + 1)
    off = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    near = np.linalg.norm(np.maximum(np.abs(off) - 1, 0), axis=1) * c <= grid.distance * (1 + 1e-3)
    sure = np.linalg.norm(np.abs(off) + 1, axis=1) * c < grid.distance * (1 - 1e-3)
    out = np.zeros(int(np.prod(dims)), dtype=np.int8)
    for label, offsets in ((1, off[near]), (2, off[sure])):
        for o in offsets @ strides:
            out[occupied + o] = label
    return out


@pytest.mark.parametrize("write", [1, 1 << 12, _GridOverlapScore.WRITE])
def test_grid_built_in_large_writes_is_the_same(write, monkeypatch):
    monkeypatch.setattr(_GridOverlapScore, "WRITE", write)
    src, tgt, _ = _problem(7, 400, 0.5)
    grid = _GridOverlapScore(src, tgt, 0.05, torch.float32, torch.device("cpu"))
    grid._build()
    assert np.array_equal(grid.grid, _grid_offset_by_offset(grid))


def test_best_hypotheses_squared_distances_skip_out_points_bit_for_bit():
    """The batch's best hypotheses' summed squared distances, as the previous implementation summed them
    (a KD-tree query of every point, np.bincount in point order)."""
    rng = np.random.default_rng(8)
    src, _, _ = _problem(8, 1500, 0.5)
    s = src[rng.integers(0, len(src), 2500)]  # with repeats
    tgt = s + rng.normal(scale=0.01, size=s.shape)
    rotations = np.stack([random_rotation(rng, 0.3 if k % 2 else 0.01) for k in range(24)])
    R = torch.as_tensor(rotations, dtype=torch.float32)
    t = torch.as_tensor(rng.normal(scale=0.02, size=(24, 3)), dtype=torch.float32)
    R[5], t[5] = torch.eye(3), torch.zeros(3)
    R[11], t[11] = R[5], t[5]  # a tie for the best
    grid = _GridOverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    count, err = grid(R, t, 0)
    top = np.nonzero(count.numpy() == int(count.max()))[0]
    assert len(top) >= 2
    q = grid.src[None] @ R[top].transpose(1, 2) + t[top][:, None, :]
    d, _ = grid.tree.query(q.reshape(-1, 3).double().numpy(), k=1, distance_upper_bound=0.05)
    inl = d < 0.05
    e = np.where(inl, d * d, 0.0) * np.tile(grid.weight, len(top))
    previous = np.bincount(np.repeat(np.arange(len(top)), len(grid.weight)), weights=e, minlength=len(top))
    assert np.array_equal(err.numpy()[top], previous)


def test_building_the_grid_at_once_gives_the_same_results(monkeypatch):
    src, tgt, corr = _problem(9, 800, 0.12)
    cfg = RansacConfig(max_iterations=10000)
    now = ransac(src, tgt, corr, cfg, seed=1)
    monkeypatch.setattr(_GridOverlapScore, "WARM", 16)  # the previous setting: the chunked scorer first
    before = ransac(src, tgt, corr, cfg, seed=1)
    assert np.array_equal(now.transform, before.transform)
    assert (now.iterations, now.n_checked, now.n_inliers) == (before.iterations, before.n_checked, before.n_inliers)


def test_squared_distances_on_request_choose_as_given_ones():
    """:class:`_Best` with the grid's counts alone (squared distances asked for only at a tie) takes the same
    hypotheses, with the same squared RMSE, as with the squared distances of ``__call__``."""
    rng = np.random.default_rng(11)
    src, _, _ = _problem(11, 1200, 0.5)
    tgt = src + rng.normal(scale=0.01, size=src.shape)
    rotations = np.stack([random_rotation(rng, 0.2 if k % 2 else 0.01) for k in range(16)])
    R = torch.as_tensor(rotations, dtype=torch.float32)
    t = torch.as_tensor(rng.normal(scale=0.01, size=(16, 3)), dtype=torch.float32)
    R[3], t[3] = torch.eye(3), torch.zeros(3)
    R[6], t[6] = R[3], t[3]  # a tie within the batch
    grid = _GridOverlapScore(src, tgt, 0.05, torch.float32, torch.device("cpu"))
    given, asked = _Best(), _Best(grid.errors)
    for batch in (slice(0, 8), slice(8, 16), slice(6, 7), slice(0, 2)):  # ties across batches too
        Rb, tb = R[batch], t[batch]
        count, err = grid(Rb, tb, given.count)
        assert given.offer(Rb, tb, count, err) == asked.offer(Rb, tb, grid.counts(Rb, tb, asked.count), None)
        assert given.count == asked.count and given.err2() == asked.err2()


def test_coarse_grid_first_gives_the_same_results(monkeypatch):
    src, tgt, corr = _problem(12, 900, 0.1)
    cfg = RansacConfig(max_iterations=8000, max_validation=300, confidence=1.0)
    results = []
    for fine_after in (0, 100, 10**9):  # fine grid at once, coarse then fine, coarse throughout
        monkeypatch.setattr(_GridOverlapScore, "FINE_AFTER", fine_after)
        r = ransac(src, tgt, corr, cfg, seed=2)
        results.append((r.transform, r.iterations, r.n_checked, r.n_inliers, r.inlier_rmse))
    for r in results[1:]:
        assert np.array_equal(r[0], results[0][0]) and r[1:] == results[0][1:]


def test_grid_of_a_box_with_far_off_target_points_is_exact():
    """Target points far off (bad depth) make the box too large: the grid covers the central points, ringed by
    *maybe* cells; its classes stay exact (points near the far ones included) and RANSAC's results the same."""
    rng = np.random.default_rng(13)
    src, tgt, corr = _problem(13, 1500, 0.3)
    tgt = tgt.copy()
    tgt[:6] = rng.uniform(-1, 1, size=(6, 3)) + [0.0, 0.0, 70.0]  # 70 m off
    grid = _GridOverlapScore(src, tgt, 0.05, torch.float32, torch.device("cpu"))
    assert grid._frame(grid.tree.data, 0.05)[4] > 0  # the band
    grid._build()
    pts = np.concatenate([tgt[rng.integers(0, len(tgt), 3000)] + rng.normal(scale=0.03, size=(3000, 3)),
                          tgt[:6] + rng.normal(scale=0.02, size=(6, 3))])  # near the far points too
    probe = _GridOverlapScore(pts, tgt, 0.05, torch.float32, torch.device("cpu"))
    probe.__dict__.update({k: getattr(grid, k) for k in ("grid", "origin", "dims", "cell", "strides")})
    probe.src_t = np.ascontiguousarray(probe.src.numpy().T)
    states = probe._states(torch.eye(3)[None], torch.zeros(1, 3))[0].numpy()
    true, _ = grid.tree.query(probe.src.double().numpy(), k=1)
    assert (true[states == 2] < 0.05).all() and (true[states == 0] >= 0.05).all()
    far = probe.src[:, 2].numpy() > 60
    assert far.sum() >= 6 and (states[far] > 0).all() and (states == 2).mean() > 0.05  # near the far points: maybe
    cfg = RansacConfig(max_iterations=5000, max_validation=200, confidence=1.0)
    a = ransac(src, tgt, corr, cfg, seed=4)
    b = ransac(src, tgt, corr, dataclasses.replace(cfg, prune=False), seed=4)
    assert np.array_equal(a.transform, b.transform) and (a.iterations, a.n_checked) == (b.iterations, b.n_checked)


@pytest.mark.parametrize("window,fit", [(0, 0), (2048, 1), (1 << 20, 1000)])
def test_hypotheses_drawn_checked_and_fitted_by_windows_are_those_of_single_batches(window, fit, monkeypatch):
    """The same results with windows of draws edge-checked together and samples fitted together as batch by
    batch (window 0), and a caller's generator left where batch-by-batch drawing leaves it (an early exit
    inside a window included)."""
    monkeypatch.setattr(_Hypotheses, "WINDOW", window)
    monkeypatch.setattr(_Hypotheses, "FIT", fit)
    out = []
    for seed, ratio in ((14, 0.4), (15, 0.08)):  # an early exit, and a run through max_iterations
        src, tgt, corr = _problem(seed, 700, ratio)
        rng = np.random.default_rng(seed)
        r = ransac(src, tgt, corr, RansacConfig(max_iterations=6000), seed=rng)
        out.append((r.transform, r.iterations, r.n_checked, r.n_inliers, rng.integers(1 << 30)))
    monkeypatch.setattr(_Hypotheses, "WINDOW", 0)
    monkeypatch.setattr(_Hypotheses, "FIT", 0)
    for (seed, ratio), got in zip(((14, 0.4), (15, 0.08)), out):
        src, tgt, corr = _problem(seed, 700, ratio)
        rng = np.random.default_rng(seed)
        r = ransac(src, tgt, corr, RansacConfig(max_iterations=6000), seed=rng)
        assert np.array_equal(r.transform, got[0])
        assert (r.iterations, r.n_checked, r.n_inliers, rng.integers(1 << 30)) == got[1:]
    assert out[0][1] < 6000 and out[1][1] == 6000
