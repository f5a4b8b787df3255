"""Predator network and its losses on hand-made cases with known values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pcrcg.errors import ConfigError
from pcrcg.models.datamodule import PairCollate
from pcrcg.models.kpconv import PyramidSpec, calibrate_limits
from pcrcg.models.losses import (
    LossConfig,
    PredatorLoss,
    circle_loss,
    descriptor_hit_rate,
    matchability_labels,
    overlap_labels,
    weighted_bce,
)
from pcrcg.models.predator import CrossAttention, Predator, PredatorConfig, build_predator, knn_indices
from pcrcg.testing.pairs import toy_pair

TINY = dict(voxel_size=0.12, num_layers=3, first_dim=16, final_dim=8, gnn_dim=16, num_heads=2, dgcnn_k=4)


@pytest.fixture(scope="module")
def batch():
    s = toy_pair(0, density=150.0)
    spec = PyramidSpec(0.12, 3, 2.5)
    spec = PyramidSpec(0.12, 3, 2.5, calibrate_limits([s.src_points, s.tgt_points], spec))
    return PairCollate(spec, overlap_radius=0.18)([s])


# --------------------------------------------------------------------------- network


def test_forward_shapes_and_ranges(batch):
    torch.manual_seed(0)
    net = build_predator(TINY, in_dim=1)
    n0 = batch.pyramid.points[0].shape[0]
    with torch.no_grad():
        out = net(torch.ones(n0, 1), batch.pyramid)
    assert out.descriptors.shape == (n0, 8)
    torch.testing.assert_close(out.descriptors.norm(dim=1), torch.ones(n0), rtol=1e-5, atol=1e-5)
    for s in (out.overlap, out.matchability):
        assert s.shape == (n0,) and float(s.min()) >= 0 and float(s.max()) <= 1
    torch.testing.assert_close(out.overlap, torch.sigmoid(out.overlap_logits))
    # the two fragments interact: changing the target's features changes the source's descriptors
    feats = torch.ones(n0, 1)
    feats[batch.n_src:] = 2.0
    with torch.no_grad():
        out2 = net(feats, batch.pyramid)
    assert not torch.allclose(out.descriptors[: batch.n_src], out2.descriptors[: batch.n_src])


def test_architecture_matches_predator_3dmatch_widths():
    net = Predator(PredatorConfig())  # 4 levels, 128 first features, 256-wide attention
    blocks = [type(b).__name__ for b in net.encoder]
    assert blocks == ["SimpleBlock"] + ["ResnetBottleneckBlock"] * 10
    assert net.encoder[0].conv.weights.shape == (15, 1, 64)
    assert net.encoder[-1].unary2.mlp.out_features == 1024
    assert net.bottle.in_features == 1024 and net.bottle.out_features == 256
    lin = [m for m in net.decoder if hasattr(m, "mlp")]
    assert [(m.mlp.in_features, m.mlp.out_features) for m in lin] == [(770, 129), (385, 64), (192, 34)]
    assert net.gnn.names == ["self", "cross", "self"]
    # kernel radii scale with the level: 2.5 voxels x 2^l, extent 2 voxels x 2^l
    assert net.encoder[0].conv.radius == pytest.approx(0.0625)
    assert net.encoder[-1].conv.extent == pytest.approx(0.025 * 2.0 * 8)


def test_in_dim_changes_only_the_first_layer():
    a = build_predator(TINY, in_dim=1).state_dict()
    b = build_predator(TINY, in_dim=1 + 32).state_dict()
    assert a.keys() == b.keys()
    differ = [k for k in a if a[k].shape != b[k].shape]
    assert differ == ["encoder.0.conv.weights"]
    assert b["encoder.0.conv.weights"].shape == (15, 33, 8)


def test_bad_sizes_name_the_setting():
    with pytest.raises(ConfigError, match="model.num_heads"):
        build_predator({**TINY, "gnn_dim": 30, "num_heads": 4})
    with pytest.raises(ConfigError, match="model.num_layers"):
        build_predator({**TINY, "num_layers": 1})


def test_knn_excludes_self():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [3.5, 0, 0]])
    idx = knn_indices(pts, 2)
    assert idx.tolist() == [[1, 2], [0, 2], [3, 1], [2, 1]]


# --------------------------------------------------------------------------- losses


def _two_by_two(pos_d: float, neg_d: float):
    coords = torch.tensor([[0.0, 1.0], [1.0, 0.0]])  # diagonal = positives, off-diagonal = negatives
    feats = torch.tensor([[pos_d, neg_d], [neg_d, pos_d]], requires_grad=True)
    return coords, feats


def test_circle_loss_known_values():
    # As Predator's code: entries outside the positive (negative) mask enter each logsumexp with a
    # logit of 0, i.e. exp(0) = 1. Optimal pairs have zero weights, so each row is log(1 + 1):
    # softplus(2 log 2) / 24 = ln(5) / 24.
    coords, feats = _two_by_two(0.1, 1.4)
    val = circle_loss(coords, feats, pos_radius=0.5, safe_radius=0.8, log_scale=24)
    assert float(val) == pytest.approx(math.log(5) / 24, rel=1e-6)
    # d_p = 0.5 -> w_p = 0.4, logit 24*0.4*0.4 = 3.84; d_n = 1.0 -> w_n = 0.4, logit 24*0.4*0.4 = 3.84
    coords, feats = _two_by_two(0.5, 1.0)
    val = circle_loss(coords, feats, pos_radius=0.5, safe_radius=0.8, log_scale=24)
    lse = math.log(math.exp(3.84) + 1)
    assert float(val) == pytest.approx(math.log1p(math.exp(2 * lse)) / 24, rel=1e-6)
    val.backward()
    assert float(feats.grad[0, 0]) > 0 and float(feats.grad[0, 1]) < 0  # pull positives, push negatives


def test_circle_loss_ignores_rows_without_negatives():
    coords = torch.tensor([[0.0, 0.05], [1.0, 0.0]])  # row 0 / column 1 have no negative beyond 0.8
    feats = torch.tensor([[0.5, 1.0], [1.0, 0.5]])
    val = circle_loss(coords, feats, 0.5, 0.8, log_scale=24)
    # only row 1 and column 0 count; each has one positive (logit 3.84) and one negative (3.84)
    lse = math.log(math.exp(3.84) + 1)
    assert float(val) == pytest.approx(math.log1p(math.exp(2 * lse)) / 24, rel=1e-6)
    assert float(circle_loss(torch.zeros(2, 2), feats, 0.5, 0.8)) == 0.0  # no negatives at all


def test_weighted_bce_known_value():
    labels = torch.tensor([1.0, 0.0, 0.0, 0.0])
    logits = torch.zeros(4)  # p = 0.5 everywhere, bce = ln 2; w+ = 0.75, w- = 0.25
    assert float(weighted_bce(logits, labels)) == pytest.approx((0.75 + 3 * 0.25) / 4 * math.log(2), rel=1e-6)
    confident = torch.tensor([10.0, -10.0, -10.0, -10.0])
    assert float(weighted_bce(confident, labels)) < 1e-4


def test_matchability_and_overlap_labels():
    src = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    tgt = src.clone()
    d_src = torch.eye(3)
    d_tgt = torch.eye(3)[[0, 2, 1]]  # target points 1 and 2 have swapped descriptors
    ls, lt = matchability_labels(src, tgt, d_src, d_tgt, radius=0.1)
    assert ls.tolist() == [1.0, 0.0, 0.0] and lt.tolist() == [1.0, 0.0, 0.0]
    corr = torch.tensor([[0, 1], [2, 0]])
    assert overlap_labels(3, 2, corr, torch.device("cpu")).tolist() == [1, 0, 1, 1, 1]


def test_descriptor_hit_rate():
    coords = torch.tensor([[0.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]])
    feats = torch.tensor([[0.1, 0.5, 0.9], [0.2, 0.9, 0.9], [0.3, 0.4, 0.5]])
    # rows 0 and 1 have a true positive; row 0's best feature is the positive, row 1's is not
    assert float(descriptor_hit_rate(coords, feats, 0.5)) == pytest.approx(0.5)


def test_predator_loss_on_perfect_and_random_outputs():
    rng = np.random.default_rng(0)
    pts = torch.from_numpy(rng.uniform(0, 2, (60, 3)).astype(np.float32))
    T = torch.eye(4)
    T[:3, 3] = torch.tensor([0.5, 0.0, 0.0])
    src = pts[:40] - T[:3, 3]  # src mapped by T onto the first 40 target points
    tgt = pts
    points = torch.cat([src, tgt])
    corr = torch.stack([torch.arange(40), torch.arange(40)], 1)
    crit = PredatorLoss(LossConfig(pos_radius=0.5, safe_radius=4.0, overlap_radius=0.5, matchability_radius=1.0),
                        voxel_size=0.02)
    desc = torch.nn.functional.normalize(torch.randn(60, 16), dim=1)
    perfect = torch.cat([desc[:40], desc])  # corresponding points share descriptors
    ov = torch.cat([torch.full((40,), 8.0), torch.full((40,), 8.0), torch.full((20,), -8.0)])
    good = crit(perfect, ov, torch.full((100,), 8.0), points, 40, T, corr)
    bad = crit(torch.nn.functional.normalize(torch.randn(100, 16), dim=1), -ov, torch.zeros(100), points, 40, T,
               corr)
    assert float(good["recall"]) == 1.0 and float(good["overlap_loss"]) < 1e-3
    assert float(good["overlap_precision"]) == 1.0 and float(good["overlap_recall"]) == 1.0
    assert float(good["matchability_recall"]) == 1.0
    assert float(good["circle_loss"]) < float(bad["circle_loss"])
    assert float(bad["overlap_loss"]) > 1.0
    assert float(good["n_corr"]) == 40
    skip = crit(perfect, ov, torch.full((100,), 8.0), points, 40, T, corr, matchability=False)
    assert "matchability_recall" not in skip and float(skip["matchability_loss"]) == 0.0
    assert float(skip["loss"]) == pytest.approx(float(good["loss"] - good["matchability_loss"]), abs=1e-6)


@pytest.mark.parametrize("profile", ["tiny", "cpu", "paper"])
def test_profiles_build_a_model(profile):
    from pcrcg.benchmarks.model import profile_config

    cfg = profile_config(profile)
    m, t = cfg["model"], cfg["trainer"]
    paper_optim = {"name": "sgd", "lr": 0.005, "momentum": 0.98, "weight_decay": 1e-6, "lr_decay": 0.95,
                   "encoder_lr_scale": 1.0, "schedule": "exponential", "warmup_steps": 0}
    # the paper's optimiser, except the cpu profile's 1,800 steps: Adam 2e-3, x0.75 per epoch (measured in
    # conf/profile/cpu.yaml)
    expected = {**paper_optim, "name": "adam", "lr": 0.002, "lr_decay": 0.75} if profile == "cpu" else paper_optim
    assert t["optim"] == expected
    assert t["batch_size"] == 1 and t["log_every_n_steps"] <= 50
    if profile == "paper":  # Predator's published 3DMatch sizes
        assert (m["voxel_size"], m["num_layers"], m["first_dim"], m["gnn_dim"], m["final_dim"]) == (
            0.025, 4, 128, 256, 32)
        assert t["max_epochs"] >= 30 and t["augment"]["rotation_range_deg"] == 360
    net = build_predator(m, in_dim=1)
    assert net.cfg.num_layers == m["num_layers"] and net.cfg.voxel_size == m["voxel_size"]


# --------------------------------------------------------------------------- match strength


def test_cross_strength_reads_how_well_a_point_matches():
    torch.manual_seed(0)
    att = CrossAttention(8, 2, strength=True)
    assert att.mlp1.in_features == 2 * 8 + 2 and CrossAttention(8, 2).mlp1.in_features == 16
    with torch.no_grad():  # queries and keys = the features themselves, so similarity is their dot product
        for lin in (att.q, att.k):
            lin.weight.copy_(torch.eye(8))
            lin.bias.zero_()
    seen = []
    att.mlp1.register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach()))
    other = torch.nn.functional.normalize(torch.randn(20, 8), dim=1) * 3
    x = torch.stack([other[4], -other[4], torch.zeros(8)])  # matches a point there, its opposite, nothing
    out = att(x, other)
    strength = seen[-1][:, 16:]  # (3, heads)
    q = x.view(3, 2, 4).transpose(0, 1)
    k = other.view(20, 2, 4).transpose(0, 1)
    expected = (torch.logsumexp(q @ k.transpose(1, 2) / 2.0, -1) - math.log(20)).t()
    torch.testing.assert_close(strength, expected)
    assert (strength[0] > strength[1]).all() and torch.allclose(strength[2], torch.zeros(2))
    assert out.shape == (3, 8)
    out.sum().backward()
    assert att.q.weight.grad is not None and float(att.q.weight.grad.abs().sum()) > 0  # the strength trains q


def test_cross_strength_is_a_model_setting(batch):
    torch.manual_seed(0)
    net = build_predator({**TINY, "cross_strength": True}, in_dim=1)
    assert net.cfg.cross_strength and all(layer.strength for layer in net.gnn.layers if isinstance(layer, CrossAttention))
    assert not any(getattr(layer, "strength", False) for layer in build_predator(TINY, in_dim=1).gnn.layers)
    out = net(torch.ones(batch.pyramid.points[0].shape[0], 1), batch.pyramid)
    assert torch.isfinite(out.overlap_logits).all()


# --------------------------------------------------------------------------- coarse losses


def test_coarse_overlap_labels_are_shares_of_level0_points():
    from pcrcg.models.losses import coarse_overlap_labels

    fine = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0, 1.0])
    assign = torch.tensor([0, 0, 1, 1, 3, 3])  # coarse point 2 has no level-0 point, 3 = none
    lab, has = coarse_overlap_labels(fine, assign, 3)
    torch.testing.assert_close(lab, torch.tensor([0.5, 1.0, 0.0]))
    assert has.tolist() == [True, True, False]


def test_coarse_assignment_follows_the_decoder_upsampling(batch):
    from pcrcg.models.module import coarse_inputs

    net = build_predator(TINY, in_dim=1)
    n0 = batch.pyramid.points[0].shape[0]
    with torch.no_grad():
        out = net(torch.ones(n0, 1), batch.pyramid)
    co = coarse_inputs(out, batch.pyramid, 0.12)
    nc = len(batch.pyramid.points[-1])
    assert co.assign.shape == (n0,) and co.voxel == pytest.approx(0.48)
    assert out.coarse_logits.shape == (nc,) and out.coarse_feats.shape == (nc, TINY["gnn_dim"])
    ok = co.assign < nc
    assert float(ok.float().mean()) > 0.95
    # source level-0 points go to source coarse points, target to target
    ns_c = co.n_src
    assert bool((co.assign[: batch.n_src][ok[: batch.n_src]] < ns_c).all())
    assert bool((co.assign[batch.n_src:][ok[batch.n_src:]] >= ns_c).all())
    # a level-0 point is near its coarse point (within two coarse cells)
    d = (batch.pyramid.points[0][ok] - batch.pyramid.points[-1][co.assign[ok]]).norm(dim=1)
    assert float(d.max()) < 2 * 0.48


def test_coarse_losses_are_off_by_default_and_reach_the_bottleneck(batch):
    from pcrcg.models.losses import CoarseInputs
    from pcrcg.models.module import coarse_inputs

    torch.manual_seed(0)
    n0 = batch.pyramid.points[0].shape[0]
    cfg = dict(pos_radius=1.5, safe_radius=4.0, overlap_radius=1.5, matchability_radius=2.0, max_points=10**6)
    off = PredatorLoss(LossConfig(**cfg), voxel_size=0.12)
    on = PredatorLoss(LossConfig(**cfg, w_coarse_overlap=1.0, w_coarse_circle=1.0), voxel_size=0.12)
    net = build_predator(TINY, in_dim=1)
    args = (batch.pyramid.points[0], batch.n_src, batch.transform, batch.corr)
    out = net(torch.ones(n0, 1), batch.pyramid)
    co = coarse_inputs(out, batch.pyramid, 0.12)
    s = on(out.descriptors, out.overlap_logits, out.matchability_logits, *args, coarse=co)
    base = off(out.descriptors, out.overlap_logits, out.matchability_logits, *args)
    assert "coarse_overlap_loss" not in base
    assert float(s["loss"]) == pytest.approx(float(base["loss"] + s["coarse_overlap_loss"]
                                                   + s["coarse_circle_loss"]), rel=1e-5)
    with pytest.raises(ValueError, match="w_coarse"):
        on(out.descriptors, out.overlap_logits, out.matchability_logits, *args)
    # the coarse terms alone send gradients into the overlap attention and the score projection
    (s["coarse_overlap_loss"] + s["coarse_circle_loss"]).backward()
    for p in (net.proj_score.weight, net.proj_gnn.weight, net.bottle.weight):
        assert float(p.grad.abs().sum()) > 0
    # and they are minimised by the right outputs: free coarse logits and features, fitted by Adam
    logits = torch.zeros_like(co.logits, requires_grad=True)
    feats = torch.randn_like(co.feats).requires_grad_(True)
    opt = torch.optim.Adam([logits, feats], lr=0.1)
    first = None
    for _ in range(60):
        c = on.coarse_losses(CoarseInputs(logits, feats, co.points, co.n_src, co.assign, co.voxel),
                             overlap_labels(batch.n_src, n0 - batch.n_src, batch.corr, logits.device), batch.transform)
        total = c["coarse_overlap_loss"] + c["coarse_circle_loss"]
        first = float(total) if first is None else first
        opt.zero_grad()
        total.backward()
        opt.step()
    assert float(total) < 0.3 * first and float(c["coarse_recall"]) > 0.9


@pytest.mark.parametrize("key,value", [("w_coarse_overlap", -1.0), ("w_overlap", "a"), ("pos_radius", 0.0)])
def test_bad_loss_settings_name_the_setting(key, value):
    with pytest.raises(ConfigError, match=f"model.loss.{key}"):
        LossConfig(**{key: value})


@pytest.mark.slow
def test_paper_sized_networks_train_and_evaluate_on_the_cpu(tiny_root, tmp_path):
    """The paper profile's networks (Predator's published sizes, the Res50 UNet with 128 channels at half
    resolution) through the real stages of a run, as a lent GPU's check runs them (``pcrcg.benchmarks.gpu_check``,
    here on the CPU): two training steps of geometry-only Predator and of PCR-CG (deep, implicit) and an
    evaluation each, on the tiny data (``profile=paper`` itself has never run: no GPU has been lent; ~60 s here)."""
    import json

    from pcrcg.benchmarks.gpu_check import check
    from pcrcg.models.train import read_checkpoint

    res = check(tmp_path, device="cpu", steps=2, eval_pairs=2, skip=("tests", "model"), data_root=tiny_root,
                timeout=600)
    for name in ("predator", "pcrcg"):
        run = res["run"][name]
        assert run["rc"] == 0, run["tail"]
        assert json.loads((tmp_path / f"run-{name}" / "pcrcg_status.json").read_text())["status"] == "finished"
        assert run["timings"]["time/train_s"] > 0 and run["metrics"]
    (ckpt,) = (tmp_path / "ck-pcrcg").rglob("last.ckpt")
    text = json.dumps(read_checkpoint(ckpt)["hyper_parameters"])
    assert '"first_dim": 128' in text and '"num_layers": 4' in text and '"arch": "resnet50"' in text
    assert "run pcrcg (paper-sized networks" in (tmp_path / "gpu_check.md").read_text()
