"""The evaluation's shortcuts give what the reference path gives, bit for bit.

* descriptor matching with row identifiers (each distinct sampled point matched once) vs plain;
* RANSAC's shortcuts to the overlap score (``RansacConfig(prune=True)``: the voxel grid that decides most
  points without the KD-tree, repeated points scored once, hopeless hypotheses abandoned; the chunked
  scorer where the grid would be too large) vs scoring every point of every hypothesis;
* the pipeline end to end (sampling with replacement, both RANSAC budgets, mutual or not).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.geometry import random_rotation
from pcrcg.registration import FragmentOutput, RegistrationConfig, register_features
from pcrcg.registration.matching import first_occurrences, match_descriptors
from pcrcg.registration.ransac import (RansacConfig, _GridOverlapScore, _OverlapScore, _PrunedOverlapScore,
                                      ransac)
from pcrcg.testing.pairs import correspondence_problem


def test_first_occurrences_maps_every_row_to_its_ids_first_position():
    ids = np.array([7, 3, 7, 9, 3, 3, 1])
    pos, row = first_occurrences(ids)
    assert pos.tolist() == [0, 1, 3, 6]  # first 7, first 3, 9, 1: in position order
    assert np.array_equal(ids[pos][row], ids)


@pytest.mark.parametrize("mutual", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matching_with_ids_equals_plain_matching(mutual, seed):
    rng = np.random.default_rng(seed)
    ds = rng.normal(size=(300, 16)).astype(np.float32)
    dt = rng.normal(size=(250, 16)).astype(np.float32)
    dt[10] = dt[200]  # two distinct target points with identical descriptors: the first position wins
    ds[5] = ds[17]
    si, ti = rng.integers(0, 300, 700), rng.integers(0, 250, 600)  # samples with replacement
    a, b = ds[si], dt[ti]
    plain = match_descriptors(a, b, mutual=mutual)
    fast = match_descriptors(a, b, mutual=mutual, src_ids=si, tgt_ids=ti)
    assert np.array_equal(plain, fast)
    if mutual:  # repeated source rows: only a row's first copy can be its target's mutual neighbour
        assert len(np.unique(si[plain[:, 0]])) == len(plain)


def _clouds(seed: int, n: int = 1500, inlier_ratio: float = 0.3):
    return correspondence_problem(seed, n, inlier_ratio)


def test_pruned_overlap_score_keeps_every_count_that_can_win():
    rng, src, tgt, _ = _clouds(0)
    s = src[rng.integers(0, len(src), 2500)]  # with repeats
    R = torch.as_tensor(np.stack([random_rotation(rng, 0.3 if k % 2 else 0.02) for k in range(40)]), dtype=torch.float32)
    t = torch.as_tensor(rng.normal(scale=0.05, size=(40, 3)), dtype=torch.float32)
    R[7], t[7] = torch.eye(3), torch.zeros(3)  # the right one (source and target are one cloud)
    tgt = s + np.random.default_rng(1).normal(scale=0.01, size=s.shape)
    full = _OverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    pruned = _PrunedOverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    c_full, e_full = full(R, t)
    for floor in (0, int(c_full.max()) // 2, int(c_full.max())):
        c, e = pruned(R, t, floor)
        kept = c >= 0
        assert kept.any() and int(c.max()) == int(c_full.max())
        assert torch.equal(c[kept], c_full[kept].to(c.dtype))
        assert torch.allclose(e[kept], e_full[kept].to(e.dtype), rtol=1e-9)
        # every abandoned hypothesis is below a count that is reached
        assert bool((c_full[~kept] < max(floor, int(c_full.max()))).all())
    assert int((pruned(R, t, 0)[0] < 0).sum()) > 0  # the shortcut does abandon hopeless ones


@pytest.mark.parametrize("max_validation", [1000, None])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_ransac_pruned_equals_reference(seed, max_validation):
    rng, src, tgt, corr = _clouds(seed, inlier_ratio=[0.5, 0.2, 0.08, 0.03][seed])
    kw = dict(max_validation=max_validation, confidence=1.0 if max_validation else 0.999, max_iterations=20000)
    ref = ransac(src, tgt, corr, RansacConfig(prune=False, **kw), seed=seed)
    new = ransac(src, tgt, corr, RansacConfig(prune=True, prune_min_points=0, **kw), seed=seed)
    assert np.array_equal(ref.transform, new.transform)
    assert (ref.iterations, ref.n_checked, ref.n_inliers) == (new.iterations, new.n_checked, new.n_inliers)


def _outputs(rng, pts, noise):
    d = np.cos(pts @ rng.normal(scale=12.0, size=(3, 24)) + 0.3) + rng.normal(scale=noise, size=(len(pts), 24))
    return FragmentOutput(pts.astype(np.float32), d.astype(np.float32), rng.uniform(0.2, 1, len(pts)),
                          rng.uniform(0.2, 1, len(pts)))


@pytest.mark.parametrize("mutual", [False, True])
@pytest.mark.parametrize("fewer_points", ["with_replacement", "whole"])
def test_pipeline_results_do_not_change(mutual, fewer_points, monkeypatch):
    import pcrcg.registration.feature_registration as P

    rng, src, tgt, _ = _clouds(5, n=900)
    a = _outputs(np.random.default_rng(1), src, 0.3)
    b = _outputs(np.random.default_rng(2), src, 0.3)  # same world points: descriptors agree
    b = FragmentOutput(tgt.astype(np.float32), b.descriptors, b.overlap, b.matchability)
    results = {}
    for new in (False, True):
        if not new:
            plain = P.match_descriptors
            monkeypatch.setattr(P, "match_descriptors",
                                lambda x, y, src_ids=None, tgt_ids=None, **kw: plain(x, y, **kw))
        else:
            monkeypatch.undo()
        cfg = RegistrationConfig(fewer_points=fewer_points, mutual=mutual,
                                 ransac=RansacConfig(max_validation=1000, confidence=1.0, max_iterations=10000,
                                                     prune=new, prune_min_points=0))
        results[new] = [register_features(a, b, n, cfg, seed=n) for n in (2000, 500)]
    for r0, r1 in zip(results[False], results[True]):
        assert np.array_equal(r0.transform, r1.transform)
        assert np.array_equal(r0.correspondences, r1.correspondences)
        assert (r0.ransac.iterations, r0.ransac.n_checked) == (r1.ransac.iterations, r1.ransac.n_checked)


def test_grid_cell_classes_are_exact():
    """Every point of an *in* cell has a target point nearer than the threshold, no point of an *out*
    cell has one, and both classes decide a real share of the points."""
    rng = np.random.default_rng(3)
    tgt = rng.uniform(0, 1.0, size=(3000, 3)) * [2.0, 1.5, 0.3]  # a slab, ~7 cm apart like the sampled N
    src = tgt[rng.integers(0, len(tgt), 20000)] + rng.normal(scale=0.02, size=(20000, 3))
    src[:2000] = rng.uniform(-1.0, 3.0, size=(2000, 3))  # far off too, outside the grid included
    d = 0.05
    grid = _GridOverlapScore(src, tgt, d, torch.float32, torch.device("cpu"))
    grid._build()
    states = grid._states(torch.eye(3)[None], torch.zeros(1, 3))[0].numpy()
    true, _ = grid.tree.query(grid.src.double().numpy(), k=1)
    assert (true[states == 2] < d).all() and (true[states == 0] >= d).all()
    share = np.bincount(states, minlength=3) / len(states)
    assert share[0] > 0.05 and share[2] > 0.3, share


@pytest.mark.parametrize("seed", [0, 1])
def test_grid_overlap_score_keeps_every_count_that_can_win(seed):
    rng, src, tgt, _ = _clouds(seed)
    s = src[rng.integers(0, len(src), 2500)]  # with repeats
    R = torch.as_tensor(np.stack([random_rotation(rng, 0.3 if k % 2 else 0.02) for k in range(40)]), dtype=torch.float32)
    t = torch.as_tensor(rng.normal(scale=0.05, size=(40, 3)), dtype=torch.float32)
    R[7], t[7] = torch.eye(3), torch.zeros(3)  # the right one (source and target are one cloud)
    R[9], t[9] = R[7], t[7]  # a tie for the best
    tgt = s + np.random.default_rng(1).normal(scale=0.01, size=s.shape)
    full = _OverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    grid = _GridOverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    c_full, e_full = full(R, t)
    best = int(c_full.max())
    for floor in (0, best // 2, best, best + 1):
        c, e = grid(R, t, floor)
        kept = c >= 0
        if floor > best:  # nothing can beat the floor
            assert not kept.any()
            continue
        assert int(c.max()) == best and torch.equal(c[kept], c_full[kept].to(c.dtype))
        top = c == best
        assert int(top.sum()) >= 2 and torch.allclose(e[top], e_full[top].to(e.dtype), rtol=1e-9)
        assert bool((c_full[~kept] < max(floor, best)).all())  # every dropped one is below a reached count
    assert int((grid(R, t, 0)[0] < 0).sum()) > 0  # hopeless hypotheses are dropped


@pytest.mark.parametrize("wide", [False, True])
def test_grid_bounds_are_the_weighted_counts_of_in_and_maybe_points(wide, monkeypatch):
    """``_bounds`` (float32 products of the states and their squares; float64 for a large total weight) gives
    the weights of the *in* points and of the *in* + *maybe* points exactly, repeated source points included."""
    rng, src, tgt, _ = _clouds(0)
    grid = _GridOverlapScore(src[rng.integers(0, len(src), 3000)], tgt, 0.05, torch.float32, torch.device("cpu"))
    if wide:  # as if the weights summed past 2**22: the float64 path
        monkeypatch.setattr(grid, "total", 1 << 23)
    states = torch.as_tensor(rng.choice(np.array([0, 1, 2], np.int8), size=(64, len(grid.weight))))
    low, high = grid._bounds(states)
    s = states.numpy()
    assert grid.weight.max() > 1  # repeats: weighted
    assert np.array_equal(low, ((s == 2) * grid.weight).sum(1)) and np.array_equal(high, ((s > 0) * grid.weight).sum(1))
    assert grid._w.dtype == (torch.float64 if wide else torch.float32)


def test_grid_settles_losing_hypotheses_with_fewer_queries(monkeypatch):
    """The *maybe* points go to the KD-tree chunk by chunk and a hypothesis stops once it cannot reach the bar:
    the same counts as querying them all at once, with fewer queries."""
    rng, src, tgt, _ = _clouds(1)
    s = src[rng.integers(0, len(src), 2500)]
    tgt = s + np.random.default_rng(1).normal(scale=0.01, size=s.shape)
    R = torch.as_tensor(np.stack([random_rotation(rng, 0.05) for _ in range(48)]), dtype=torch.float32)
    t = torch.as_tensor(rng.normal(scale=0.04, size=(48, 3)), dtype=torch.float32)
    R[5], t[5] = torch.eye(3), torch.zeros(3)
    grid = _GridOverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))
    queried = []
    tree_query = grid.tree.query

    class Counting:
        data = grid.tree.data

        def query(self, x, **kw):
            queried.append(len(x))
            return tree_query(x, **kw)

    grid._build()
    monkeypatch.setattr(grid, "tree", Counting())
    states = grid._states(R, t).numpy()
    low, high = grid._bounds(torch.from_numpy(states))
    group = np.flatnonzero(high >= 0)
    maybe = states[group] == 1
    level = int(_OverlapScore(s, tgt, 0.05, torch.float32, torch.device("cpu"))(R, t)[0].max())
    settled = grid._settle(R, t, group, maybe, low[group], high[group], level)
    hyp, pts, d = grid._query(R, t, group, maybe)
    at_once = low[group] + np.bincount(hyp, weights=grid.weight[pts] * (d < 0.05), minlength=len(group)).astype(np.int64)
    kept = settled >= 0
    assert kept[5] and settled[5] == level  # the right one
    assert np.array_equal(settled[kept], at_once[kept])
    assert (at_once[~kept] < level).all() and (~kept).sum() > 0
    assert sum(queried[:-1]) < queried[-1]  # chunk by chunk, fewer than all at once


def test_overlap_scorer_choice_with_the_same_results(monkeypatch):
    """The grid scorer by default; where the grid would be too large, the chunked scorer from
    ``prune_min_points`` source points and the reference below; the results are the same every way."""
    used = []

    def recording(init, name):
        def wrapped(self, *args, **kwargs):
            used.append(name)
            init(self, *args, **kwargs)
        return wrapped

    for cls in (_OverlapScore, _PrunedOverlapScore, _GridOverlapScore):
        monkeypatch.setattr(cls, "__init__", recording(cls.__init__, cls.__name__))
    _, src, tgt, corr = _clouds(6, n=1200, inlier_ratio=0.2)
    kw = dict(max_validation=500, confidence=1.0, max_iterations=5000)
    results = {}
    cases = (("grid", RansacConfig(**kw), _GridOverlapScore.MAX_CELLS),
             ("small", RansacConfig(**kw), 1), ("chunked", RansacConfig(prune_min_points=1000, **kw), 1),
             ("off", RansacConfig(prune=False, **kw), _GridOverlapScore.MAX_CELLS))
    for label, cfg, cells in cases:
        monkeypatch.setattr(_GridOverlapScore, "MAX_CELLS", cells)
        used.clear()
        results[label] = (ransac(src, tgt, corr, cfg, seed=3), set(used))
    assert RansacConfig().prune_min_points == 2000
    assert results["grid"][1] == {"_GridOverlapScore", "_PrunedOverlapScore"}  # the grid builds on the chunked one
    assert results["small"][1] == {"_OverlapScore"}  # 1200 < 2000 points
    assert results["chunked"][1] == {"_PrunedOverlapScore"}
    assert results["off"][1] == {"_OverlapScore"}
    ref = results["off"][0]
    for label in ("grid", "small", "chunked"):
        r = results[label][0]
        assert np.array_equal(r.transform, ref.transform)
        assert (r.iterations, r.n_checked, r.n_inliers) == (ref.iterations, ref.n_checked, ref.n_inliers)
