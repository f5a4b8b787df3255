"""The projection module on known geometry: exact pixels, occlusion, windows, views, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.data.dataset import View
from pcrcg.errors import ConfigError
from pcrcg.geometry import axis_angle_to_matrix, make_transform, transform_points
from pcrcg.lifting import (
    ColorLifter,
    LiftingConfig,
    ViewKeypoints,
    build_lifter,
    lift_pair,
    pair_coverage,
    window_weight_map,
)
from pcrcg.testing.scenes import make_pair
from pcrcg.vision.encoders import ResUNet
from pcrcg.vision.features import FeatureExtractor
from pcrcg.vision.matching import MatcherConfig, match_views

H, W = 12, 16
K = np.array([[10.0, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])


def plane_view(pose: np.ndarray, depth: float = 2.0, seed: int = 0) -> View:
    """A camera looking at a fronto-parallel wall ``depth`` metres away."""
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    return View(color, np.full((H, W), depth, np.float32), K.copy(), pose, 0, f"<plane{seed}>")


def pixel_point(view: View, u: int, v: int, z: float) -> np.ndarray:
    """The fragment-frame point seen at pixel (u, v) at camera depth z."""
    pc = np.array([[(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z]])
    return transform_points(view.pose, pc)[0]


POSE = make_transform(axis_angle_to_matrix([0.3, -1.0, 0.2], 0.7), np.array([0.4, -0.2, 1.1]))


def lifter(projection="implicit", views=1, window=3, tol=0.1):
    return ColorLifter(LiftingConfig(projection, "rgb", views, window, tol))


def test_point_takes_exactly_its_pixels_feature():
    view = plane_view(POSE)
    fmap = torch.randn(5, H, W)
    pix = [(0, 0), (15, 11), (7, 5), (3, 9), (12, 2)]
    pts = torch.tensor(np.stack([pixel_point(view, u, v, 2.0) for u, v in pix]), dtype=torch.float32)
    L = ColorLifter(LiftingConfig("implicit", "sift", 1, feature_dim=5))
    feats, cov = L(pts, [view], feature_maps=[fmap])
    assert cov.all()
    for k, (u, v) in enumerate(pix):
        assert torch.equal(feats[k], fmap[:, v, u]), (u, v)
    # rgb: exactly the pixel's color
    feats, _ = lifter()(pts, [view])
    for k, (u, v) in enumerate(pix):
        assert torch.allclose(feats[k], torch.tensor(view.color[v, u] / 255.0, dtype=torch.float32))


def test_occluded_outside_and_holes_get_nothing():
    view = plane_view(POSE)
    view.depth[3, 4] = 0.0  # a hole in the depth map
    pts = np.stack([
        pixel_point(view, 7, 5, 2.0),    # on the wall: covered
        pixel_point(view, 7, 5, 3.0),    # behind the wall at the same pixel: occluded
        pixel_point(view, 7, 5, 2.08),   # within the depth tolerance
        pixel_point(view, 7, 5, 1.5),    # in front of the wall (free space): rejected too
        pixel_point(view, 40, 5, 2.0),   # outside the image
        pixel_point(view, 7, 5, -2.0),   # behind the camera
        pixel_point(view, 4, 3, 2.0),    # depth hole
    ])
    feats, cov = lifter()(torch.tensor(pts, dtype=torch.float32), [view])
    assert cov.tolist() == [True, False, True, False, False, False, False]
    assert torch.all(feats[~cov] == 0)
    expect = torch.tensor(view.color[5, 7] / 255.0, dtype=torch.float32)
    assert torch.allclose(feats[0], expect) and torch.allclose(feats[2], expect)


def test_views_are_averaged_and_cover_more():
    a = plane_view(np.eye(4), seed=1)
    shift = make_transform(np.eye(3), np.array([1.0, 0.0, 0.0]))  # second camera 1 m to the right
    b = plane_view(shift, seed=2)
    p_both = pixel_point(a, 10, 6, 2.0)  # x = 0.5 m: pixel u=10 in a, u=5 in b
    p_a_only = pixel_point(a, 1, 6, 2.0)
    pts = torch.tensor(np.stack([p_both, p_a_only]), dtype=torch.float32)
    fa, fb = torch.randn(4, H, W), torch.randn(4, H, W)
    one = ColorLifter(LiftingConfig("implicit", "sift", 1, feature_dim=4))
    two = ColorLifter(LiftingConfig("implicit", "sift", 2, feature_dim=4))
    f1, c1 = one(pts, [a, b], feature_maps=[fa, fb])
    f2, c2 = two(pts, [a, b], feature_maps=[fa, fb])
    assert c1.tolist() == [True, True] and c2.tolist() == [True, True]
    ub = 5
    assert torch.allclose(f2[0], 0.5 * (fa[:, 6, 10] + fb[:, 6, ub]))
    assert torch.equal(f2[1], fa[:, 6, 1])  # seen by a only: not diluted by b
    assert torch.equal(f1[0], fa[:, 6, 10])
    # a point only b sees: uncovered with 1 view, covered with 2
    p_b = torch.tensor(pixel_point(b, 14, 6, 2.0)[None], dtype=torch.float32)
    assert not one(p_b, [a, b], feature_maps=[fa, fb])[1][0]
    assert two(p_b, [a, b], feature_maps=[fa, fb])[1][0]


def test_explicit_window_and_confidence():
    view = plane_view(POSE)
    fmap = torch.randn(3, H, W)
    kp = ViewKeypoints(np.array([[7.2, 5.4]]), np.array([0.5]))  # rounds to pixel (7, 5)
    pix = [(7, 5), (8, 6), (6, 4), (9, 5), (7, 8), (10, 5)]
    pts = torch.tensor(np.stack([pixel_point(view, u, v, 2.0) for u, v in pix]), dtype=torch.float32)
    covered = {}
    for w in (1, 3, 5, 7):
        L = ColorLifter(LiftingConfig("explicit", "sift", 1, w, feature_dim=3))
        f, c = L(pts, [view], [kp], feature_maps=[fmap])
        covered[w] = c.tolist()
        for k, (u, v) in enumerate(pix):
            expect = 0.5 * fmap[:, v, u] if c[k] else torch.zeros(3)
            assert torch.allclose(f[k], expect)
    assert covered[1] == [True, False, False, False, False, False]
    assert covered[3] == [True, True, True, False, False, False]
    assert covered[5] == [True, True, True, True, False, False]
    assert covered[7] == [True, True, True, True, True, True]
    # no keypoints: explicit lifts nothing; implicit ignores keypoints
    L = ColorLifter(LiftingConfig("explicit", "sift", 1, 7, feature_dim=3))
    assert not L(pts, [view], [None], feature_maps=[fmap])[1].any()
    with pytest.raises(ValueError, match="explicit projection needs"):
        L(pts, [view], None, feature_maps=[fmap])


def test_window_map_overlap_takes_highest_confidence():
    m = window_weight_map(np.array([[3, 3], [5, 3], [100, 100]]), np.array([0.2, 0.9, 1.0]), (8, 10), 3)
    assert m[3, 2] == pytest.approx(0.2) and m[3, 4] == pytest.approx(0.9) and m[3, 6] == pytest.approx(0.9)
    assert m[3, 7] == 0 and m.sum() == pytest.approx(0.2 * 6 + 0.9 * 9)  # 3x3 windows at u=3 and u=5 share column 4


def test_official_windows_are_the_official_codes_slices():
    """``window_style=official``: ``map[int(x - w):int(x + w), int(y - w):int(y + w)] = confidence`` on the official
    code's (W, H) array, match by match, with w = (window_size - 1) // 2, transposed to the (H, W) grid."""
    uv = np.array([[50.3, 40.7], [53.0, 44.0], [2.0, 60.0], [158.6, 3.2]])
    conf = np.array([0.9, 0.2, 0.7, 0.4], np.float32)
    m = window_weight_map(uv, conf, (120, 160), 11, style="official").numpy()
    ref = np.zeros((160, 120), np.float32)  # written here as the official loop does, with Python's slices
    for (x, y), c in zip(uv, conf):
        ref[int(x - 5):int(x + 5), int(y - 5):int(y + 5)] = c
    assert np.array_equal(m, ref.T)
    # 10 x 10 pixels from int(x - 5): columns 45..54, rows 35..44; the later, weaker match overwrites the overlap
    assert m[35, 45] == pytest.approx(0.9) and m[44, 47] == pytest.approx(0.9) and m[45, 46] == 0 and m[35, 55] == 0
    assert m[39, 48] == pytest.approx(0.2) and m[39, 57] == pytest.approx(0.2)
    # a start below 0 wraps (columns [-3:7] of 160) to an empty slice: the match at u = 2 colors nothing, nor
    # does the one at v = 3.2 (rows [-1:8])
    assert not m[:, :10].any() and not m[:, 150:].any()
    assert np.count_nonzero(m) == 100 + 100 - 6 * 7  # the two windows share rows 39..44 x columns 48..54
    centred = window_weight_map(uv, conf, (120, 160), 11).numpy()
    assert centred[40, 50] == pytest.approx(0.9) and centred[36:47, 45:56].min() > 0  # 11 x 11 around (50, 41)
    assert centred[60, 2] == pytest.approx(0.7)  # the border match keeps its clipped window


def test_window_style_setting():
    assert LiftingConfig("explicit", "sift", 1, 11, feature_dim=3).window_style == "centred"
    with pytest.raises(ConfigError, match="projection.window_style"):
        LiftingConfig("explicit", "sift", 1, 11, feature_dim=3, window_style="square")
    with pytest.raises(ConfigError, match="projection.window_size.*official"):
        LiftingConfig("explicit", "sift", 1, 1, feature_dim=3, window_style="official")
    # the implicit projection draws no windows: any size goes with either style (the official style is the default)
    assert LiftingConfig("implicit", "sift", 1, 1, feature_dim=3, window_style="official").window_size == 1
    with pytest.raises(ValueError, match="window style"):
        window_weight_map(np.zeros((1, 2)), np.ones(1), (4, 4), 3, style="square")
    # a lifter reads it: the official 3 is a 2 x 2 window from int(u - 1) (pixels 6..7 x 4..5 around (7.2, 5.4))
    view = plane_view(POSE)
    fmap = torch.randn(3, H, W)
    kp = ViewKeypoints(np.array([[7.2, 5.4]]), np.array([0.5]))
    pix = [(6, 4), (7, 5), (8, 5), (7, 6)]
    pts = torch.tensor(np.stack([pixel_point(view, u, v, 2.0) for u, v in pix]), dtype=torch.float32)
    L = ColorLifter(LiftingConfig("explicit", "sift", 1, 3, feature_dim=3, window_style="official"))
    assert L(pts, [view], [kp], feature_maps=[fmap])[1].tolist() == [True, True, False, False]
    L = ColorLifter(LiftingConfig("explicit", "sift", 1, 3, feature_dim=3))
    assert L(pts, [view], [kp], feature_maps=[fmap])[1].tolist() == [True, True, True, True]


def test_projection_grid_resampling():
    """A coarser grid (image_size) scales intrinsics, depth and features consistently."""
    view = plane_view(POSE)
    fmap = torch.arange(H * W, dtype=torch.float32).view(1, H, W).repeat(2, 1, 1)
    p = torch.tensor(pixel_point(view, 9, 7, 2.0)[None], dtype=torch.float32)  # grid (6, 8): pixel (4, 3)
    L = ColorLifter(LiftingConfig("implicit", "sift", 1, feature_dim=2, image_size=(6, 8)))
    f, c = L(p, [view], feature_maps=[fmap])
    assert c[0]
    # bilinear 2x downsampling of pixel (4, 3) averages pixels u in {8, 9}, v in {6, 7}
    assert f[0, 0].item() == pytest.approx(float(fmap[0, 6:8, 8:10].mean()))


def test_config_validation_names_the_setting():
    cases = [
        (dict(window_size=0), "projection.window_size"),
        (dict(window_size=4), "projection.window_size"),
        (dict(views=5), "projection.views"),
        (dict(views=0), "projection.views"),
        (dict(projection="sideways"), "projection.name"),
        (dict(features="hog"), "features.name"),
        (dict(features="rgb", feature_dim=8), "features.dim"),
        (dict(depth_tolerance=0), "projection.depth_tolerance"),
        (dict(image_size=(10,)), "projection.image_size"),
    ]
    for kw, setting in cases:
        with pytest.raises(ConfigError) as e:
            LiftingConfig(**kw)
        assert e.value.setting == setting, kw
    assert LiftingConfig("none", "deep").out_dim == 0
    assert LiftingConfig("explicit", "none").out_dim == 0
    assert LiftingConfig("implicit", "rgb").out_dim == 3
    assert LiftingConfig("explicit", "deep", feature_dim=64).out_dim == 64
    assert LiftingConfig("explicit", "sift").out_dim == 32
    cfg = LiftingConfig.from_cfg({"projection": {"name": "explicit", "views": 3, "window_size": 17},
                                  "features": {"name": "sift", "dim": 16}})
    assert (cfg.views, cfg.window_size, cfg.out_dim) == (3, 17, 16)
    with pytest.raises(ConfigError) as e:
        LiftingConfig.from_cfg({"projection": {"name": "explicit", "window_size": 2.5}, "features": {"name": "rgb"}})
    assert e.value.setting == "projection.window_size"


def test_out_dim_zero_when_nothing_is_lifted():
    s = make_pair(0)
    L = ColorLifter(LiftingConfig("none", "rgb"))
    r = lift_pair(L, s)
    assert r.src_feats.shape == (len(s.src_points), 0) and r.color_coverage == 0.0


@pytest.fixture(scope="module")
def toy():
    s = make_pair(0)
    return s, match_views(s.src_views, s.tgt_views, MatcherConfig())


def test_coverage_grows_with_views_and_window(toy):
    s, m = toy
    cov = {v: pair_coverage(lifter("implicit", v), s) for v in (1, 2, 3)}
    assert 0.5 < cov[1] < cov[2] <= cov[3]
    assert cov[2] > 0.95  # the paper: "with two views, most points are covered"
    exp = {v: pair_coverage(lifter("explicit", v, 11), s, m) for v in (1, 2, 3)}
    assert 0 < exp[1] < exp[2] <= exp[3] < cov[3]
    win = [pair_coverage(lifter("explicit", 2, w), s, m) for w in (3, 7, 11, 17)]
    assert all(a < b for a, b in zip(win, win[1:])), win


def test_lift_pair_rgb_matches_point_colors(toy):
    s, m = toy
    r = lift_pair(lifter("implicit", 2), s)
    assert r.src_feats.shape == (len(s.src_points), 3)
    assert r.color_coverage == pytest.approx(
        (int(r.src_covered.sum()) + int(r.tgt_covered.sum())) / (len(s.src_points) + len(s.tgt_points)))
    # the lifted colors are the surface colors of the points (up to texture interpolation)
    err = (r.src_feats[r.src_covered] - torch.from_numpy(s.src_colors)[r.src_covered]).abs().mean()
    assert err < 0.03
    e = lift_pair(lifter("explicit", 2, 11), s, m)
    assert e.n_matches == len(m[(0, 0)]) + len(m[(1, 1)])
    assert e.color_coverage < r.color_coverage


def test_gradients_reach_the_encoder(toy):
    s, m = toy
    torch.manual_seed(0)
    enc = ResUNet("resnet18", 8)
    ext = FeatureExtractor("deep", 8, encoder=enc, image_size=(60, 80))
    L = ColorLifter(LiftingConfig("explicit", "deep", 2, 11, feature_dim=8), ext)
    r = lift_pair(L, s, m)
    assert r.src_feats.shape == (len(s.src_points), 8) and r.src_feats.requires_grad
    loss = r.src_feats.square().sum() + r.tgt_feats.sum()
    loss.backward()
    for name in ("encoder.conv1.weight", "encoder.layer4.1.conv2.weight", "decoder.head.weight"):
        g = dict(enc.named_parameters())[name].grad
        assert g is not None and g.abs().sum() > 0, name
    # uncovered points contribute no gradient
    assert not r.src_feats[~r.src_covered].any()
    assert sum(p.numel() for p in L.parameters()) == sum(p.numel() for p in enc.parameters())


def test_build_lifter_from_config(tmp_path):
    cfg = {
        "projection": {"name": "explicit", "views": 2, "window_size": 7, "depth_tolerance": 0.1, "image_size": None},
        "features": {"name": "sift", "dim": 8},
        "encoder2d": {"name": "scratch", "arch": "resnet18", "out_dim": 8},
        "matcher2d": {"method": "orb", "cache_dir": str(tmp_path / "m")},
    }
    L = build_lifter(cfg)
    assert L.out_dim == 8 and L.matcher.method == "orb" and L.extractor.kind == "sift"
    s = make_pair(2)
    r = L.lift_pair(s)
    assert r.src_feats.shape == (len(s.src_points), 8) and 0 < r.color_coverage < 1
    assert L.match_cache.misses == 2 and len(list((tmp_path / "m").rglob("*.npz"))) == 2
    cfg["features"] = {"name": "deep", "dim": 8}
    deep = build_lifter(cfg).extractor
    assert type(deep.encoder).__name__ == "ResUNet" and deep.encoder.arch == "resnet18" and deep.encoder.out_dim == 8
