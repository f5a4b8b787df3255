"""Feature maps: rgb, dense SIFT (reduced, deterministic), deep (encoder output with gradients)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.errors import ConfigError
from pcrcg.testing.scenes import make_pair
from pcrcg.vision import features
from pcrcg.vision.encoders import ResUNet
from pcrcg.vision.features import FeatureExtractor, build_feature_extractor, dense_sift_map, rgb_map, sift_projection


@pytest.fixture(scope="module")
def pair():
    return make_pair(1)


def test_rgb_map_is_exact():
    img = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    m = rgb_map(img)
    assert m.shape == (3, 7, 9) and m.dtype == torch.float32
    assert torch.allclose(m[:, 4, 2], torch.tensor(img[4, 2] / 255.0, dtype=torch.float32))


def test_sift_projection_is_fixed_and_orthonormal():
    P = sift_projection(24, seed=5)
    assert P.shape == (24, 128)
    assert np.allclose(P @ P.T, np.eye(24), atol=1e-5)
    assert np.array_equal(P, sift_projection(24, seed=5))
    assert not np.allclose(P, sift_projection(24, seed=6))
    with pytest.raises(ConfigError):
        sift_projection(200)


def test_dense_sift_map(pair):
    img = pair.src_views[0].color
    m = dense_sift_map(img, dim=16, step=4)
    assert m.shape == (16, 120, 160)
    assert torch.equal(m, dense_sift_map(img, dim=16, step=4))
    # step 3: keypoints sit on pixels 1, 4, 7, ...; there the map is the unit-norm reduced descriptor,
    # in between it is interpolated (norm below 1)
    m3 = dense_sift_map(img, dim=16, step=3)
    norms = m3.norm(dim=0)
    assert torch.allclose(norms[1::3, 1::3], torch.ones(40, 53), atol=1e-5)
    assert norms[2::3, 2::3].mean() < 0.995
    # different content gives different descriptors, a shifted image shifts them
    other = dense_sift_map(pair.tgt_views[1].color, dim=16, step=4)
    assert (m - other).abs().mean() > 0.05
    shifted = np.ascontiguousarray(np.roll(img, 8, axis=1))
    ms = dense_sift_map(shifted, dim=16, step=4)
    assert (ms[:, 30:90, 48:120] - m[:, 30:90, 40:112]).abs().mean() < 0.2 * (m - other).abs().mean()


def test_extractor_kinds(pair):
    views = pair.src_views[:2]
    assert FeatureExtractor("none", 0)(views) == []
    rgb = FeatureExtractor("rgb", 3)(views)
    assert len(rgb) == 2 and rgb[0].shape == (3, 120, 160)
    sift = build_feature_extractor({"name": "sift", "dim": 8, "step": 4})(views)
    assert sift[1].shape == (8, 120, 160)
    with pytest.raises(ConfigError):
        FeatureExtractor("rgb", 5)
    with pytest.raises(ConfigError):
        FeatureExtractor("hog", 5)
    with pytest.raises(ConfigError):
        FeatureExtractor("deep", 8, encoder=None)


def test_deep_maps_are_memoised_in_eval_mode_and_recomputed_when_the_weights_change(pair, monkeypatch):
    """Evaluation reuses a view's map (a fragment is in several pairs); the maps equal one batched call
    over all the views; a lone new view is encoded beside another (a batch of two); training mode,
    gradients and an optimiser step all bypass or invalidate the memo."""
    torch.manual_seed(0)
    enc = ResUNet("resnet18", 8)
    ext = FeatureExtractor("deep", 8, encoder=enc, image_size=(60, 80))
    batches: list[int] = []
    enc.register_forward_hook(lambda mod, args, out: batches.append(int(args[0].shape[0])))
    views = list(pair.src_views[:2] + pair.tgt_views[:2])
    ext.eval()
    with torch.no_grad():
        ref = ext._encode(views, "cpu")  # one batched call, no memo
        batches.clear()
        first = ext(views[:2])
        both = ext(views)
        again = ext(views[2:] + views[:1])
        lone = ext([views[1], views[3]])  # both known: no call
    assert batches == [2, 2]  # src views, then the two tgt views; nothing after
    for got, want in zip(first + both + again + lone, ref[:2] + ref + ref[2:] + ref[:1] + [ref[1], ref[3]]):
        assert torch.allclose(got, want, rtol=0, atol=1e-6)
    ext._deep_memo.clear()
    with torch.no_grad():
        batches.clear()
        ext(views[:1])
    assert batches == [2]  # a lone miss is encoded in a batch of two (itself twice here)
    monkeypatch.setattr(features, "DEEP_MEMO_BYTES", 1)  # a bound: only the last call's maps stay
    with torch.no_grad():
        ext(views[1:3])
    assert len(ext._deep_memo) == 2
    # gradients on, or training mode: the encoder runs every time (and training mode frees the memo)
    batches.clear()
    ext(views[:2])
    ext.train()
    assert not ext._deep_memo
    with torch.no_grad():
        ext(views[:2])
    assert batches == [2, 2]
    # an optimiser step changes the weights: the memo is forgotten, the maps follow the new weights
    ext.eval()
    with torch.no_grad():
        before = ext(views[:2])
    opt = torch.optim.SGD(enc.parameters(), lr=1e-3)
    ext.train()
    ext(views[:2])[0].mean().backward()
    opt.step()
    ext.eval()
    with torch.no_grad():
        batches.clear()
        after = ext(views[:2])
        fresh = ext._encode(views[:2], "cpu")
    assert batches == [2, 2] and torch.isfinite(after[0]).all() and not torch.allclose(before[0], after[0])
    assert torch.allclose(after[0], fresh[0], rtol=0, atol=1e-6)


def test_a_detached_per_image_net_reuses_each_views_map_while_training(pair):
    """bn_stats=per_image: the net's output does not depend on its mode, so without gradients (a detached
    2D net) each view is encoded once, in training too, and the memo outlives train(); the maps are
    bit-identical to those of the pair's own batched call; memo_mb=0 turns the memo off."""
    from pcrcg.vision.features import mode_dependent

    torch.manual_seed(0)
    enc = ResUNet("resnet18", 8, bn_stats="per_image")
    assert not mode_dependent(enc) and mode_dependent(ResUNet("resnet18", 8))
    ext = FeatureExtractor("deep", 8, encoder=enc, image_size=(60, 80))
    batches: list[int] = []
    enc.register_forward_hook(lambda mod, args, out: batches.append(int(args[0].shape[0])))
    views = list(pair.src_views[:2] + pair.tgt_views[:2])
    ext.train()
    with torch.no_grad():
        ref = ext._encode(views, "cpu")
        batches.clear()
        first = ext(views)
        ext.eval()
        ext.train()  # a validation pass and back: the maps stay
        again = ext(views[2:] + views[:2])
    assert batches == [4] and len(ext._deep_memo) == 4
    for got, want in zip(first + again, ref + ref[2:] + ref[:2]):
        assert torch.equal(got, want)
    # with gradients (end to end) the net runs every time
    batches.clear()
    ext(views[:2])
    assert batches == [2]
    # off
    off = build_feature_extractor({"name": "deep", "dim": 8},
                                  {"name": "scratch", "arch": "resnet18", "bn_stats": "per_image", "memo_mb": 0})
    with torch.no_grad():
        off(views[:2])
    assert off.memo_bytes == 0 and not off._deep_memo
    on = build_feature_extractor({"name": "deep", "dim": 8}, {"name": "scratch", "memo_mb": 1.5})
    assert on.memo_bytes == int(1.5 * 2**20)
    for bad in (-1, "lots", True):
        with pytest.raises(ConfigError, match="encoder2d.memo_mb"):
            build_feature_extractor({"name": "deep", "dim": 8}, {"name": "scratch", "memo_mb": bad})


def test_deep_extractor_resizes_and_keeps_gradients(pair):
    torch.manual_seed(0)
    enc = ResUNet("resnet18", 8)
    ext = FeatureExtractor("deep", 8, encoder=enc, image_size=(60, 80))
    maps = ext(pair.src_views[:2] + pair.tgt_views[:1])
    assert len(maps) == 3 and maps[0].shape == (8, 60, 80)
    maps[0].sum().backward()
    assert enc.encoder.conv1.weight.grad is not None and enc.encoder.conv1.weight.grad.abs().sum() > 0
    with pytest.raises(ConfigError):
        FeatureExtractor("deep", 16, encoder=enc)  # width must be the encoder's


def test_sift_grids_are_memoised_per_view_within_the_bound_and_give_the_same_maps(pair, monkeypatch):
    """features=sift computes a view's SIFT once (its grid, ~1/16 of the map) and upsamples it at every
    use: the maps are dense_sift_map's bit for bit; encoder2d.memo_mb bounds the grids kept (the oldest
    go first), 0 keeps none."""
    views = list(pair.src_views[:2] + pair.tgt_views[:2])
    want = [dense_sift_map(v.color, dim=8, step=4) for v in views]
    calls: list[int] = []
    grid = features.dense_sift_grid
    monkeypatch.setattr(features, "dense_sift_grid", lambda color, *a: calls.append(1) or grid(color, *a))
    ext = build_feature_extractor({"name": "sift", "dim": 8, "step": 4}, {"memo_mb": 1})
    for rnd in range(3):
        got = ext(views[:2]) + ext(views[2:]) + ext(views[1:2])
        assert all(torch.equal(g, w) for g, w in zip(got, want + want[1:2]))
    assert len(calls) == 4  # each view's SIFT once over the three rounds
    g_bytes = ext._sift_grids[next(iter(ext._sift_grids))].numel() * 4
    assert ext._sift_bytes == 4 * g_bytes  # (8, 30, 40) float32 each, far below 1 MB
    # a bound of two grids: the oldest go; the maps stay the same
    ext = FeatureExtractor("sift", 8, memo_bytes=2 * g_bytes)
    calls.clear()
    assert all(torch.equal(g, w) for g, w in zip(ext(views) + ext(views[2:]), want + want[2:]))
    assert len(calls) == 4 and list(ext._sift_grids) == [ext._memo_key(v) for v in views[2:]]
    ext = build_feature_extractor({"name": "sift", "dim": 8, "step": 4}, {"memo_mb": 0})  # no memo
    calls.clear()
    assert all(torch.equal(g, w) for g, w in zip(ext(views) + ext(views), want + want))
    assert len(calls) == 8 and not ext._sift_grids
    with pytest.raises(ConfigError, match="encoder2d.memo_mb"):
        build_feature_extractor({"name": "sift"}, {"memo_mb": -1})
