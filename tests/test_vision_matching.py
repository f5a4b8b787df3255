"""2D matcher: geometric correctness on a scene with known poses, settings, the disk cache."""

from __future__ import annotations

import os

import numpy as np
import pytest

from pcrcg.errors import ConfigError
from pcrcg.geometry import invert, project, transform_points
from pcrcg.testing.scenes import make_pair
from pcrcg.vision.matching import MatchCache, MatcherConfig, Matches, match_images, match_views, view_pairs


@pytest.fixture(scope="module")
def pair():
    return make_pair(0)


def reprojection_error(sample, k: int, m: Matches) -> np.ndarray:
    """Pixel error of each match: uv_a lifted with src depth, moved into tgt, projected, vs uv_b."""
    va, vb = sample.src_views[k], sample.tgt_views[k]
    u = np.round(m.uv_a).astype(int)
    d = va.depth[u[:, 1], u[:, 0]].astype(np.float64)
    K = va.intrinsics
    # uv_a is sub-pixel: back-project the exact position with the depth of its pixel
    pc = np.stack([(m.uv_a[:, 0] - K[0, 2]) * d / K[0, 0], (m.uv_a[:, 1] - K[1, 2]) * d / K[1, 1], d], 1)
    p_tgt = transform_points(sample.transform @ va.pose, pc)
    uv, _ = project(transform_points(invert(vb.pose), p_tgt), vb.intrinsics)
    return np.linalg.norm(uv - m.uv_b, axis=1)


@pytest.mark.parametrize("method", ["sift", "orb"])
def test_matches_agree_with_known_geometry(pair, method):
    m = match_images(pair.src_views[0].color, pair.tgt_views[0].color, MatcherConfig(method=method))
    assert len(m) >= 20
    assert m.uv_a.dtype == np.float32 and m.uv_a.shape == (len(m), 2) and m.confidence.shape == (len(m),)
    assert np.all(m.confidence > 0) and np.all(m.confidence <= 1)
    err = reprojection_error(pair, 0, m)
    assert np.median(err) < 1.5
    assert (err < 4.0).mean() > 0.9


def test_ratio_mutual_and_ransac_filter(pair):
    a, b = pair.src_views[0].color, pair.tgt_views[0].color
    loose = match_images(a, b, MatcherConfig(ratio=1.0, mutual=False, ransac_threshold=1000.0))
    strict = match_images(a, b, MatcherConfig())
    assert len(loose) > len(strict) >= 20
    # without the ratio test many matches are wrong; the default pipeline keeps few wrong ones
    assert (reprojection_error(pair, 0, loose) > 4).mean() > 0.3
    assert (reprojection_error(pair, 0, strict) > 4).mean() < 0.1
    # an impossible ratio leaves nothing
    assert len(match_images(a, b, MatcherConfig(ratio=1e-4))) == 0


def test_identical_images_match_in_place(pair):
    img = pair.src_views[0].color
    m = match_images(img, img, MatcherConfig())
    assert len(m) > 50
    assert np.abs(m.uv_a - m.uv_b).max() < 1e-3


def test_resized_matching_reports_input_pixels(pair):
    a, b = pair.src_views[0].color, pair.tgt_views[0].color
    import cv2

    a2 = cv2.resize(a, (320, 240), interpolation=cv2.INTER_LINEAR)
    b2 = cv2.resize(b, (320, 240), interpolation=cv2.INTER_LINEAR)
    m = match_images(a2, b2, MatcherConfig(image_size=(120, 160)))
    assert len(m) >= 20
    # coordinates are in the 320x240 input: halve them (pixel-centre convention) to check against 160x120 geometry
    half = Matches((m.uv_a + 0.5) / 2 - 0.5, (m.uv_b + 0.5) / 2 - 0.5, m.confidence)
    assert np.median(reprojection_error(pair, 0, half)) < 1.5
    assert m.uv_a[:, 0].max() > 170  # really in input pixels


def test_view_pairs():
    assert view_pairs(3, 3, "paper") == [(0, 0), (1, 1), (2, 2)]
    assert view_pairs(2, 3, "paper") == [(0, 0), (1, 1)]
    assert view_pairs(2, 2, "all") == [(0, 0), (0, 1), (1, 0), (1, 1)]
    with pytest.raises(ConfigError):
        view_pairs(2, 2, "some")


def test_config_validation():
    with pytest.raises(ConfigError) as e:
        MatcherConfig(method="superglue")
    assert e.value.setting == "matcher2d.method"
    with pytest.raises(ConfigError) as e:
        MatcherConfig(ratio=1.5)
    assert e.value.setting == "matcher2d.ratio"
    with pytest.raises(ConfigError) as e:
        MatcherConfig(pairs="most")
    assert e.value.setting == "matcher2d.pairs"
    cfg = MatcherConfig.from_cfg({"method": "orb", "ratio": 0.7, "cache_dir": "x", "image_size": [120, 160]})
    assert cfg.method == "orb" and cfg.ratio == 0.7 and cfg.image_size == (120, 160)


def test_match_cache_reuses_dumps(pair, tmp_path):
    cache = MatchCache(tmp_path / "dumps")
    cfg = MatcherConfig(pairs="all")
    first = match_views(pair.src_views[:2], pair.tgt_views[:2], cfg, cache)
    assert set(first) == {(0, 0), (0, 1), (1, 0), (1, 1)}
    assert cache.misses == 4 and cache.hits == 0
    assert len(list((tmp_path / "dumps").rglob("*.npz"))) == 4
    again = MatchCache(tmp_path / "dumps")  # a new run
    second = match_views(pair.src_views[:2], pair.tgt_views[:2], cfg, again)
    assert again.hits == 4 and again.misses == 0
    for k in first:
        assert np.array_equal(first[k].uv_a, second[k].uv_a) and np.array_equal(first[k].confidence, second[k].confidence)
    # other matcher settings are other dumps
    match_views(pair.src_views[:1], pair.tgt_views[:1], MatcherConfig(method="orb"), again)
    assert again.misses == 1


def test_cache_key_follows_files(pair, tmp_path):
    from pcrcg.data.layout import write_color

    pa, pb = tmp_path / "a.color.png", tmp_path / "b.color.png"
    write_color(pa, pair.src_views[0].color)
    write_color(pb, pair.tgt_views[0].color)
    cache = MatchCache(tmp_path / "c")
    cfg = MatcherConfig()
    a, b = pair.src_views[0].color, pair.tgt_views[0].color
    cache.match(a, b, cfg, str(pa), str(pb))
    cache.match(a, b, cfg, str(pa), str(pb))
    assert (cache.hits, cache.misses) == (1, 1)
    st = pa.stat()
    os.utime(pa, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the file changed
    cache.match(a, b, cfg, str(pa), str(pb))
    assert cache.misses == 2
    # without a path the pixels are the key
    cache.match(a, b, cfg)
    cache.match(a.copy(), b.copy(), cfg)
    assert cache.misses == 3 and cache.hits == 2


def test_oracle_keeps_the_matches_the_ground_truth_confirms(pair, tmp_path):
    """matcher2d.oracle_px: true matches stay, a match moved 10 px and one without depth go; match_views
    filters after the cache (which keeps every match); no ground truth, or a bad value, is a one-line error."""
    from pcrcg.geometry import backproject
    from pcrcg.vision.matching import oracle_filter

    va, vb = pair.src_views[0], pair.tgt_views[0]
    pts, vu = backproject(va.depth, va.intrinsics, stride=9)
    T_b_a = invert(vb.pose) @ pair.transform @ va.pose
    uv_b, _ = project(transform_points(T_b_a, pts), vb.intrinsics)
    uv_a = vu[:, ::-1].astype(np.float64)
    true = Matches(uv_a, uv_b, np.ones(len(uv_a)))
    assert len(oracle_filter(true, va, vb, pair.transform, 3.0)) == len(true)
    moved = Matches(uv_a, uv_b + [[10.0, 0.0]], np.ones(len(uv_a)))
    assert len(oracle_filter(moved, va, vb, pair.transform, 3.0)) == 0
    assert len(oracle_filter(moved, va, vb, pair.transform, 11.0)) == len(true)
    holes = np.argwhere(va.depth == 0)
    if len(holes):  # a pixel without depth cannot be confirmed
        v, u = holes[0]
        assert len(oracle_filter(Matches([[u, v]], uv_b[:1], [1.0]), va, vb, pair.transform, 1e6)) == 0

    cache = MatchCache(tmp_path / "m")
    every = match_views(pair.src_views, pair.tgt_views, MatcherConfig(), cache, pair.transform)
    kept = match_views(pair.src_views, pair.tgt_views, MatcherConfig(oracle_px=1.0), cache, pair.transform)
    assert kept.keys() == every.keys() and cache.hits == len(every)  # the same dumps, read back
    for k, m in kept.items():
        assert 0 < len(m) <= len(every[k]) and np.all(reprojection_error(pair, k[0], m) < 1.0 + 1e-3)
    assert sum(map(len, kept.values())) < sum(map(len, every.values()))  # SIFT's 3 px RANSAC lets some 1-3 px through
    with pytest.raises(ConfigError) as e:
        match_views(pair.src_views, pair.tgt_views, MatcherConfig(oracle_px=3.0))
    assert e.value.setting == "matcher2d.oracle_px"
    for bad in (0, -2.0, True):
        with pytest.raises(ConfigError):
            MatcherConfig(oracle_px=bad)
    from pcrcg.config import load_run_config

    with pytest.raises(ConfigError, match="matcher2d.oracle_px"):  # caught when the run's config is read
        load_run_config(["profile=tiny", "features=deep", "projection=explicit", "matcher2d.oracle_px=0"])
    assert load_run_config(["profile=tiny"]).matcher2d.oracle_px is None  # the default: every match
