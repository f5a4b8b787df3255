"""Sampling, matching and RANSAC (pcrcg.registration)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.errors import ConfigError
from pcrcg.evaluation.metrics import rotation_error_deg
from pcrcg.geometry import make_transform, random_rotation, transform_points
from pcrcg.registration import (
    FragmentOutput,
    RansacConfig,
    RegistrationConfig,
    kabsch,
    match_descriptors,
    ransac,
    ransac_open3d,
    register_features,
    sample_indices,
)
from pcrcg.registration.feature_registration import pair_seed
from pcrcg.testing.pairs import make_fragment_pair, simulate_outputs
from pcrcg.testing.rooms import box_room


def _problem(seed: int, K: int = 2000, inlier_ratio: float = 0.5, noise: float = 0.01):
    """Correspondences on a room surface: a known transform, ``inlier_ratio`` true matches."""
    rng = np.random.default_rng(seed)
    pts, _ = box_room(rng, 3 * K)
    src = pts[rng.choice(len(pts), K, replace=False)]
    T = make_transform(random_rotation(rng), rng.normal(size=3))
    tgt = transform_points(T, src) + rng.normal(scale=noise, size=(K, 3))
    out = rng.random(K) >= inlier_ratio
    tgt[out] = transform_points(T, pts[rng.choice(len(pts), int(out.sum()))])  # wrong surface points
    corr = np.stack([np.arange(K), np.arange(K)], 1)
    return src, tgt, corr, T, ~out


def _ok(T_est, T, deg=2.0, m=0.05):
    return rotation_error_deg(T_est[:3, :3], T[:3, :3]) < deg and np.linalg.norm(T_est[:3, 3] - T[:3, 3]) < m


@pytest.mark.parametrize("score", ["overlap", "correspondences"])
def test_ransac_recovers_a_known_transform_with_half_outliers(score):
    src, tgt, corr, T, inl = _problem(0, inlier_ratio=0.5)
    res = ransac(src, tgt, corr, RansacConfig(score=score), seed=1)
    # the best 3-point hypothesis, not refitted (as Open3D): within the noise of 3 points
    assert _ok(res.transform, T, deg=1.5, m=0.04)
    assert res.fitness == pytest.approx(inl.mean(), abs=0.03)
    assert res.iterations < 50000  # early termination
    assert res.transform.shape == (4, 4) and np.allclose(res.transform[3], [0, 0, 0, 1])


def test_ransac_is_deterministic_for_a_seed():
    src, tgt, corr, _, _ = _problem(1, inlier_ratio=0.1)
    a = ransac(src, tgt, corr, seed=7)
    b = ransac(src, tgt, corr, seed=7)
    assert np.array_equal(a.transform, b.transform) and a.iterations == b.iterations


def test_ransac_runs_every_iteration_at_confidence_one_and_handles_degenerate_input():
    src, tgt, corr, T, _ = _problem(2, K=300, inlier_ratio=0.4)
    res = ransac(src, tgt, corr, RansacConfig(confidence=1.0, max_iterations=3000), seed=0)
    assert res.iterations == 3000 and _ok(res.transform, T)
    empty = ransac(src, tgt, corr[:2])
    assert np.array_equal(empty.transform, np.eye(4)) and empty.fitness == 0.0


def test_refine_does_not_lose_inliers():
    src, tgt, corr, T, _ = _problem(3, inlier_ratio=0.3)
    a = ransac(src, tgt, corr, RansacConfig(refine=0), seed=2)
    b = ransac(src, tgt, corr, RansacConfig(refine=3), seed=2)
    assert b.n_inliers >= a.n_inliers and _ok(b.transform, T, deg=1.0, m=0.02)


def test_ours_and_open3d_agree_on_the_same_correspondences():
    """Same correspondence sets, same settings: both recover the same pairs (and fail the same)."""
    ok_ours, ok_o3d = [], []
    for seed in range(6):
        ratio = [0.5, 0.2, 0.08, 0.5, 0.2, 0.08][seed]
        src, tgt, corr, T, _ = _problem(10 + seed, K=1500, inlier_ratio=ratio)
        ok_ours.append(_ok(ransac(src, tgt, corr, seed=seed).transform, T))
        ok_o3d.append(_ok(ransac_open3d(src, tgt, corr, seed=seed).transform, T))
    assert ok_ours == ok_o3d == [True] * 6
    # without any true correspondence neither can succeed
    src, tgt, corr, T, _ = _problem(20, K=800, inlier_ratio=0.0)
    assert not _ok(ransac(src, tgt, corr, seed=0).transform, T)
    assert not _ok(ransac_open3d(src, tgt, corr, seed=0).transform, T)


def test_kabsch_batched_is_exact_and_proper():
    g = torch.Generator().manual_seed(0)
    P = torch.randn(5, 4, 3, generator=g, dtype=torch.float64)
    rng = np.random.default_rng(0)
    Rs = np.stack([random_rotation(rng) for _ in range(5)])
    ts = rng.normal(size=(5, 3))
    Q = P @ torch.as_tensor(Rs).transpose(1, 2) + torch.as_tensor(ts)[:, None]
    R, t = kabsch(P, Q)
    assert np.allclose(R.numpy(), Rs, atol=1e-10) and np.allclose(t.numpy(), ts, atol=1e-10)
    assert np.allclose(torch.linalg.det(R).numpy(), 1.0)


def test_sampling_modes():
    rng = np.random.default_rng(0)
    scores = np.zeros(1000)
    scores[:100] = 1.0
    scores[100:200] = 0.01
    idx = sample_indices(scores, 100, "topk", rng)
    assert np.array_equal(idx, np.arange(100))
    p = sample_indices(scores, 100, "prob", rng)
    assert len(np.unique(p)) == 100 and (p < 100).mean() > 0.85 and (p >= 200).sum() == 0
    r = sample_indices(scores, 100, "random", rng)
    assert len(np.unique(r)) == 100 and (r >= 200).mean() > 0.6
    assert np.array_equal(sample_indices(scores[:50], 100, "prob", rng), np.arange(50))
    with pytest.raises(ConfigError, match="sampling"):
        sample_indices(scores, 10, "best", rng)
    # prob sampling is proportional: two groups with 3:1 weight are drawn about 3:1 for small n
    s = np.r_[np.full(5000, 3.0), np.full(5000, 1.0)]
    picks = np.concatenate([sample_indices(s, 20, "prob", np.random.default_rng(k)) for k in range(200)])
    assert 0.70 < (picks < 5000).mean() < 0.80


def test_matching_nearest_neighbour_and_mutual():
    a = np.array([[1, 0], [0, 1], [0.9, 0.1]], np.float32)
    b = np.array([[1, 0], [0, 1]], np.float32)
    assert match_descriptors(a, b).tolist() == [[0, 0], [1, 1], [2, 0]]
    assert match_descriptors(a, b, mutual=True).tolist() == [[0, 0], [1, 1]]
    assert match_descriptors(np.zeros((0, 2)), b).shape == (0, 2)


def test_matching_blocks_add_into_the_squared_lengths_as_the_plain_formula():
    """The nearest neighbours of descriptor matching (one product adding into |b|^2 per block) against the
    plain ``|b|^2 - 2 a.b`` and its arg-min: the same indices (ties included), values equal to rounding."""
    from pcrcg.device import argmin_rows
    from pcrcg.registration.matching import _nearest

    gen = torch.Generator().manual_seed(0)
    for n, m, d in ((700, 650, 32), (129, 40, 16)):
        a = torch.nn.functional.normalize(torch.randn(n, d, generator=gen), dim=1)
        b = torch.nn.functional.normalize(torch.randn(m, d, generator=gen), dim=1)
        b[7] = b[3]  # an exact tie: the first of equal rows wins in both
        a[:5] = b[3]
        plain = argmin_rows((b * b).sum(1)[None, :] - 2.0 * (a @ b.T))
        for chunk in (128, 50, 4096):
            assert torch.equal(_nearest(a, b, chunk), plain)
        assert _nearest(a, b, 128)[:5].tolist() == [3] * 5


def test_register_features_end_to_end_is_seeded():
    rng = np.random.default_rng(3)
    pts, cols = box_room(rng, 40000)
    pair = make_fragment_pair(rng, pts, cols, crop=0.25, voxel=0.04)
    fourier = (rng.normal(scale=1 / 0.06, size=(32, 3)), rng.uniform(0, 6.28, 32))
    ds, os_, ms = simulate_outputs(rng, pair.src_world, pair.src_overlap, 0.4, fourier=fourier)
    dt, ot, mt = simulate_outputs(rng, pair.tgt_world, np.ones(len(pair.tgt_world), bool), 0.4, fourier=fourier)
    src = FragmentOutput(pair.src_points, ds, os_, ms)
    tgt = FragmentOutput(pair.tgt_points, dt, ot, mt)
    cfg = RegistrationConfig(ransac=RansacConfig(max_iterations=20000))
    a = register_features(src, tgt, 1000, cfg, seed=5)
    b = register_features(src, tgt, 1000, cfg, seed=5)
    assert np.array_equal(a.transform, b.transform) and np.array_equal(a.src_idx, b.src_idx)
    # one SeedSequence registers the same way every time (spawning advances it: a copy is spawned from)
    ss = pair_seed(0, "scene", 0, 2, 1000)
    c, d = (register_features(src, tgt, 1000, cfg, seed=ss) for _ in range(2))
    assert np.array_equal(c.src_idx, d.src_idx) and np.array_equal(c.transform, d.transform)
    e = register_features(src, tgt, 1000, cfg, seed=pair_seed(0, "scene", 0, 2, 1000))
    assert np.array_equal(c.src_idx, e.src_idx) and ss.n_children_spawned == 0
    assert len(a.src_idx) == 1000 and a.correspondences.shape == (1000, 2)
    assert _ok(a.transform, pair.transform, deg=3.0, m=0.1)
    # correspondences index the full fragments
    assert a.correspondences[:, 0].max() < len(pair.src_points)
    with pytest.raises(ValueError, match="descriptors"):
        FragmentOutput(pair.src_points, ds[:10], os_, ms)
