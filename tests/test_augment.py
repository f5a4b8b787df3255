"""Pair augmentation keeps the views consistent: rotating cloud + cameras leaves lifting unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.data.augment import augment_pair
from pcrcg.geometry import rotation_angle_deg, transform_points
from pcrcg.lifting import ColorLifter, LiftingConfig, lift_pair
from pcrcg.testing.scenes import make_pair
from pcrcg.vision.matching import MatcherConfig, match_views


@pytest.fixture(scope="module")
def toy():
    s = make_pair(3)
    return s, match_views(s.src_views[:2], s.tgt_views[:2], MatcherConfig())


def registration_residual(s) -> float:
    """Mean distance between src points mapped by the transform and the nearest tgt point."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(s.tgt_points).query(transform_points(s.transform, s.src_points.astype(np.float64)))
    return float(np.median(d))


@pytest.mark.parametrize("which", ["src", "tgt"])
def test_transform_stays_consistent(toy, which):
    s, _ = toy
    src0, pose0, T0 = s.src_points.copy(), s.src_views[0].pose.copy(), s.transform.copy()
    rng = np.random.default_rng(0)
    a = augment_pair(s, rng, rotation_range_deg=180.0, noise_std=0.0, which=which)
    moved = a.src_points if which == "src" else a.tgt_points
    assert not np.allclose(moved, s.src_points if which == "src" else s.tgt_points)
    assert registration_residual(a) == pytest.approx(registration_residual(s), abs=1e-4)
    assert registration_residual(s) < 0.03
    # the input is untouched
    assert np.array_equal(s.src_points, src0) and np.array_equal(s.src_views[0].pose, pose0)
    assert np.array_equal(s.transform, T0)


def test_rotation_range_and_noise(toy):
    s, _ = toy
    rng = np.random.default_rng(1)
    angles = []
    for _ in range(20):
        a = augment_pair(s, rng, rotation_range_deg=30.0, noise_std=0.0)
        delta = a.transform[:3, :3] @ s.transform[:3, :3].T  # tgt rotated: R T; src rotated: T R^-1
        delta_src = s.transform[:3, :3].T @ a.transform[:3, :3]
        angles.append(min(rotation_angle_deg(delta), rotation_angle_deg(delta_src)))
    assert max(angles) <= 30.0 + 1e-6 and max(angles) > 5.0
    n = augment_pair(s, np.random.default_rng(2), rotation_range_deg=0.0, noise_std=0.01)
    assert np.std(n.src_points - s.src_points) == pytest.approx(0.01, rel=0.05)
    assert np.allclose(n.transform, s.transform)


@pytest.mark.parametrize("projection", ["implicit", "explicit"])
def test_lifted_features_unchanged_by_rotating_cloud_and_cameras(toy, projection):
    s, m = toy
    lifter = ColorLifter(LiftingConfig(projection, "rgb", views=2, window_size=11))
    before = lift_pair(lifter, s, m)
    a = augment_pair(s, np.random.default_rng(4), rotation_range_deg=360.0, noise_std=0.0, which="src")
    after = lift_pair(lifter, a, m)  # same images, so the same 2D matches
    same = torch.isclose(before.src_feats, after.src_feats, atol=1e-6).all(dim=1)
    print(f"{projection}: {int((~same).sum())} of {len(same)} points differ")
    assert same.float().mean() > 0.999  # a handful of points may sit on a pixel border
    assert (before.src_covered == after.src_covered).float().mean() > 0.999
    assert before.color_coverage > 0.2
    assert after.color_coverage == pytest.approx(before.color_coverage, abs=1e-3)
    assert torch.equal(before.tgt_feats, after.tgt_feats)
    # negative control: rotating the cloud but not its cameras destroys the lifting
    broken = a.__class__(**{**a.__dict__, "src_views": s.src_views})
    bad = lift_pair(lifter, broken, m)
    assert bad.src_covered.float().mean() < 0.5 * before.src_covered.float().mean()
