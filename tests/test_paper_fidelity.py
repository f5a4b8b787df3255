"""Issue 14: every ablation axis means what the paper's table means (the paper's text and the
official code, Gardlin/PCR-CG, and Predator's protocol, prs-eth/OverlapPredator)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from pcrcg.config import load_run_config, preflight
from pcrcg.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]


def _run_cfg(*overrides: str):
    return load_run_config(["profile=tiny", *overrides])


def _compose_evaluate(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="evaluate", overrides=["profile=tiny", *overrides])


# --------------------------------------------------------------------------- item 13: one key per setting


@pytest.mark.parametrize("mirror, primary, value", [
    ("registration.ransac.distance", "eval.ransac_distance", "0.03"),
    ("registration.ransac.max_iterations", "eval.ransac_iterations", "123"),
    ("registration.n_points", "eval.n_points", "[1000]"),
    ("projection.views", "views", "3"),
    ("projection.window_size", "window_size", "7"),
])
def test_a_mirror_set_alone_is_an_error_naming_both_keys(mirror, primary, value):
    with pytest.raises(ConfigError) as info:
        _run_cfg(f"{mirror}={value}")
    assert info.value.setting == mirror and primary in str(info.value)


def test_the_primary_key_moves_its_mirror():
    from pcrcg.evaluation.stage import configs_from

    cfg = _run_cfg("eval.ransac_distance=0.03", "eval.ransac_iterations=123", "eval.n_points=[1000]", "views=3",
                   "window_size=7")
    assert cfg.projection.views == 3 and cfg.projection.window_size == 7
    rcfg, bcfg = configs_from(cfg)
    assert rcfg.ransac.distance == 0.03 and rcfg.ransac.max_iterations == 123 and rcfg.n_points == (1000,)
    assert bcfg.ransac.distance == 0.03
    # both names set to the same value: one setting, no conflict
    cfg = _run_cfg("eval.ransac_distance=0.03", "registration.ransac.distance=0.03")
    assert configs_from(cfg)[0].ransac.distance == 0.03


def test_configs_from_refuses_two_values_instead_of_overwriting_one():
    from pcrcg.evaluation.stage import configs_from

    both = OmegaConf.create({"eval": {"ransac_distance": 0.05}, "registration": {"ransac": {"distance": 0.03}}})
    with pytest.raises(ConfigError, match="eval.ransac_distance"):
        configs_from(both)
    # python -m pcrcg.evaluate composes the registration group alone: its own value counts
    rcfg, _ = configs_from(_compose_evaluate("registration.ransac.distance=0.03"))
    assert rcfg.ransac.distance == 0.03


def test_predator_variant_reaches_the_classical_methods(tmp_path):
    from pcrcg.evaluation.metrics import load_benchmark
    from pcrcg.evaluation.stage import run_classical
    from pcrcg.data.layout import Layout
    from pcrcg.testing.layouts import write_layout

    from pcrcg.evaluation.model import subset

    root = write_layout(tmp_path / "data", seed=0, n_points=6000)
    full = load_benchmark(Layout(root).benchmark_dir("3DMatch"))
    gt = subset(full, {s: {(p.i, p.j) for p in g.pairs if p.j - p.i > 1} for s, g in full.items()})
    init = {s: {(p.i, p.j): p.transform for p in g.pairs} for s, g in gt.items()}
    counted = {}
    for variant in (False, True):
        res = run_classical("icp", root, "3DMatch", init=init, gt=gt, predator_variant=variant, progress=False)
        counted[variant] = res["score"].n_counted
    assert counted[True] == counted[False] - 1  # Predator's script never counts a scene's first pair


# --------------------------------------------------------------------------- item 6: circle loss scale


def test_circle_loss_scale_is_the_one_the_official_trainings_ran_with():
    from pcrcg.models.losses import LossConfig

    # Predator's and PCR-CG's main.py build MetricLoss(config) without log_scale: its default 16 applies
    assert LossConfig().log_scale == 16.0
    cfg = _run_cfg()
    assert cfg.model.loss.log_scale == 16
    assert LossConfig.from_mapping(cfg.model.loss).log_scale == 16
    # the configs' 24 is a setting
    assert LossConfig.from_mapping(_run_cfg("model.loss.log_scale=24").model.loss).log_scale == 24


# --------------------------------------------------------------------------- item 7: RANSAC budget


def _ransac_problem(K=400, seed=0):
    from pcrcg.geometry import make_transform, random_rotation, transform_points
    from pcrcg.testing.rooms import box_room

    rng = np.random.default_rng(seed)
    pts, _ = box_room(rng, 3 * K)
    src = pts[rng.choice(len(pts), K, replace=False)]
    T = make_transform(random_rotation(rng), rng.normal(size=3))
    tgt = transform_points(T, src) + rng.normal(scale=0.005, size=(K, 3))
    out = rng.random(K) >= 0.3
    tgt[out] = transform_points(T, pts[rng.choice(len(pts), int(out.sum()))])
    return src, tgt, np.stack([np.arange(K), np.arange(K)], 1), T


def test_open3d_010_budget_stops_after_the_validated_hypotheses():
    from pcrcg.registration import RansacConfig, ransac

    src, tgt, corr, T = _ransac_problem()
    capped = ransac(src, tgt, corr, RansacConfig(max_iterations=50000, max_validation=100, confidence=1.0), seed=0)
    assert capped.n_checked == 100 and capped.iterations < 50000
    # the same draws without the cap: the first 100 validated hypotheses are the same ones, the rest go on
    full = ransac(src, tgt, corr, RansacConfig(max_iterations=capped.iterations, confidence=1.0), seed=0)
    assert full.n_checked == 100 and np.allclose(full.transform, capped.transform)
    longer = ransac(src, tgt, corr, RansacConfig(max_iterations=50000, confidence=1.0), seed=0)
    assert longer.iterations == 50000 and longer.n_checked > 100


def test_the_run_defaults_to_the_published_numbers_ransac_budget():
    from pcrcg.evaluation.stage import _protocol, configs_from
    from pcrcg.registration import RegistrationConfig

    rcfg, bcfg = configs_from(_run_cfg())
    assert rcfg.ransac.max_validation == 1000 and rcfg.ransac.confidence == 1.0
    assert bcfg.ransac.max_validation == 1000  # FPFH + RANSAC: the same budget
    assert rcfg.ransac.budget.startswith("Open3D 0.10")
    assert _protocol(rcfg, {}, {}, 0, False)["ransac_budget"] == rcfg.ransac.budget
    early, _ = configs_from(_run_cfg("registration=early_exit"))
    assert early.ransac.max_validation is None and early.ransac.confidence == 0.999
    assert early.ransac.budget.startswith("Open3D >= 0.12")
    # Open3D's own RANSAC (>= 0.12) has no validation budget: refused, not ignored
    with pytest.raises(ConfigError, match="max_validation"):
        RegistrationConfig(backend="open3d", ransac={"max_validation": 1000})
    # the experiment that reports recall both ways
    cfg = load_run_config(["profile=tiny", "+experiment=ransac_budget", "registration=early_exit"])
    assert cfg.experiment_name == "ransac_budget" and cfg.registration.ransac.max_validation is None


# --------------------------------------------------------------------------- item 8: fragments with fewer than N points


def test_fragments_with_fewer_points_are_resampled_as_predator_does():
    from pcrcg.evaluation.stage import configs_from
    from pcrcg.registration import FragmentOutput, RegistrationConfig, register_features
    from pcrcg.registration.sampling import sample_indices

    rng = np.random.default_rng(0)
    scores = rng.random(300)
    idx = sample_indices(scores, 1000, "prob", rng, fewer="with_replacement")
    assert len(idx) == 1000 and idx.max() < 300 and len(np.unique(idx)) < 300 < len(idx)
    assert np.array_equal(sample_indices(scores, 1000, "prob", rng, fewer="whole"), np.arange(300))
    # exactly N points: all of them once, either way (Predator samples all N without replacement)
    assert np.array_equal(sample_indices(scores, 300, "prob", rng, fewer="with_replacement"), np.arange(300))
    # the run's default is Predator's; the pipeline samples N points of a small fragment
    assert configs_from(_run_cfg())[0].fewer_points == "with_replacement"
    pts = rng.normal(size=(200, 3)).astype(np.float32)
    frag = FragmentOutput(pts, rng.normal(size=(200, 8)), np.ones(200), np.ones(200))
    reg = register_features(frag, frag, 500, RegistrationConfig(fewer_points="with_replacement",
                                                                 ransac={"max_iterations": 200}))
    assert len(reg.src_idx) == 500 and len(reg.correspondences) == 500
    reg = register_features(frag, frag, 500, RegistrationConfig(fewer_points="whole", ransac={"max_iterations": 200}))
    assert len(reg.src_idx) == 200
    with pytest.raises(ConfigError, match="fewer_points"):
        RegistrationConfig(fewer_points="pad")


# --------------------------------------------------------------------------- item 9: distances tied to the voxel


@pytest.mark.parametrize("profile, voxel", [("tiny", 0.06), ("cpu", 0.06), ("paper", 0.025)])
def test_registration_distances_are_twice_the_models_voxel_and_the_metrics_stay(profile, voxel):
    from pcrcg.evaluation.stage import configs_from, thresholds_from

    cfg = load_run_config([f"profile={profile}"])
    rcfg, bcfg = configs_from(cfg)
    assert rcfg.ransac.distance == pytest.approx(2 * voxel) == pytest.approx(cfg.eval.ransac_distance)
    # FPFH + RANSAC on equal terms: the model's voxel, the same 2x threshold
    assert bcfg.fpfh.voxel == pytest.approx(voxel) and bcfg.fpfh.distance * bcfg.fpfh.voxel == pytest.approx(2 * voxel)
    # the protocol's metric thresholds do not move
    assert thresholds_from(cfg) == {"inlier_distance": 0.1, "fmr_threshold": 0.05, "rmse_threshold": 0.2}
    # a model voxel set on the command line moves them too; Open3D's FPFH recipe is a setting
    rcfg, bcfg = configs_from(load_run_config([f"profile={profile}", "model.voxel_size=0.04",
                                               "registration.fpfh.voxel=0.05", "registration.fpfh.distance=1.5"]))
    assert rcfg.ransac.distance == pytest.approx(0.08) and bcfg.fpfh.voxel == 0.05 and bcfg.fpfh.distance == 1.5


# --------------------------------------------------------------------------- item 5: unseen points, several views


def _two_views():
    H, W = 12, 16
    K = np.array([[10.0, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])

    def at(u, v, z=2.0):  # the point seen at pixel (u, v) of a camera at the origin
        return np.array([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])

    # both views see points 0 and 1 (same camera); point 2 lies behind both cameras: seen by none
    pts = torch.tensor(np.stack([at(3, 3), at(12, 8), [0.0, 0.0, -1.0]]), dtype=torch.float32)
    maps = [torch.full((4, H, W), 2.0), torch.full((4, H, W), 6.0)]
    # explicit: view 0 has a window on point 0 only, view 1 windows on both points
    w0, w1 = torch.zeros(H, W), torch.zeros(H, W)
    w0[3, 3] = 1.0
    w1[3, 3] = w1[8, 12] = 1.0
    return pts, maps, [w0, w1]


def test_unseen_points_and_several_views_follow_the_official_code_by_default():
    from pcrcg.lifting import ColorLifter, LiftingConfig

    pts, maps, weights = _two_views()
    lcfg = LiftingConfig.from_cfg(_run_cfg("features=sift", "features.dim=4", "projection=explicit",
                                           "projection.image_size=null"))
    assert (lcfg.unseen_value, lcfg.combine) == (1.0, "overwrite")
    feats, cov = ColorLifter(lcfg)(pts, _views(), weights, maps)
    # point 0: both views' windows; the first view writes last and wins (2, not the mean 4)
    assert torch.allclose(feats[0], torch.full((4,), 2.0)) and bool(cov[0])
    # point 1: the first view sees it outside its windows: its 0 wins over the second view's 6
    assert torch.allclose(feats[1], torch.zeros(4)) and not bool(cov[1])
    # point 2: seen by no view: the constant 1 (the official input is ones repeated to 129 there)
    assert torch.allclose(feats[2], torch.ones(4)) and not bool(cov[2])
    assert ColorLifter(lcfg).coverage(pts, _views(), weights).tolist() == cov.tolist()
    # the paper's text: the mean of the views that lift, zeros for every uncovered point
    mean = LiftingConfig("explicit", "sift", 2, 3, feature_dim=4, unseen_value=0.0, combine="mean")
    feats, cov = ColorLifter(mean)(pts, _views(), weights, maps)
    assert torch.allclose(feats[0], torch.full((4,), 4.0)) and torch.allclose(feats[1], torch.full((4,), 6.0))
    assert torch.allclose(feats[2], torch.zeros(4)) and cov.tolist() == [True, True, False]
    assert ColorLifter(mean).coverage(pts, _views(), weights).tolist() == cov.tolist()
    with pytest.raises(ConfigError, match="projection.combine"):
        LiftingConfig(combine="max")


def _views():
    from pcrcg.data.dataset import View

    K = np.array([[10.0, 0, 7.5], [0, 10.0, 5.5], [0, 0, 1]])
    return [View(np.zeros((12, 16, 3), np.uint8), np.full((12, 16), 2.0, np.float32), K.copy(), np.eye(4), 0, f"<v{k}>")
            for k in range(2)]


# --------------------------------------------------------------------------- item 1: 2D branch detached by default


def test_explicit_windows_are_the_official_codes_by_default():
    """The explicit projection draws its windows as the official code (``datasets/indoor.py``'s slices); the paper's
    centred N x N windows are a setting, and a config without the key (an older run's) reads as centred."""
    from pcrcg.lifting import LiftingConfig

    cfg = load_run_config(["profile=tiny", "features=deep", "projection=explicit", "encoder2d=scratch"])
    assert LiftingConfig.from_cfg(cfg).window_style == "official"
    cfg = load_run_config(["profile=tiny", "features=deep", "projection=explicit", "encoder2d=scratch",
                           "projection.window_style=centred"])
    assert LiftingConfig.from_cfg(cfg).window_style == "centred"
    assert LiftingConfig.from_cfg({"projection": {"name": "explicit"}, "features": {"name": "deep"}}).window_style \
        == "centred"


def test_the_2d_branch_is_detached_by_default_and_end_to_end_is_a_setting():
    from test_training import MODEL, _color_batch, _lifting

    from pcrcg.testing.scenes import make_pair
    from pcrcg.models.module import PCRCGModule, training_2d

    cfg = _run_cfg("features=deep", "projection=implicit")
    assert cfg.encoder2d.training == "detached"
    assert training_2d({"encoder2d": {"name": "scratch"}}) == "end_to_end"  # checkpoints made before the setting
    sample = make_pair(0, width=80, height=60, frames=3, voxel=0.05)
    batch = _color_batch(sample)
    grads = {}
    for mode in ("detached", "end_to_end"):
        lifting = {**_lifting("implicit", "deep", dim=8),
                   "encoder2d": {"name": "scratch", "arch": "resnet18", "out_dim": 8, "weights": None,
                                 "image_size": [48, 64], "training": mode}}
        torch.manual_seed(0)
        module = PCRCGModule({**MODEL, "voxel_size": 0.1}, lifting=lifting)
        loss = module.training_step(batch, 0)
        loss.backward()
        grads[mode] = [p.grad for p in module.lifter.parameters() if p.grad is not None]
        groups = module.configure_optimizers()["optimizer"].param_groups
        assert len(groups) == (1 if mode == "detached" else 2)
    assert grads["detached"] == [] and grads["end_to_end"]  # the 3D loss reaches the 2D net only end to end
    with pytest.raises(ConfigError, match="encoder2d.training"):
        _run_cfg("features=deep", "projection=implicit", "encoder2d.training=frozen")
    # the 2D backbone table sweeps both ways
    bb = OmegaConf.load(REPO / "conf" / "experiment" / "backbone_2d.yaml").hydra.sweeper.params
    assert str(bb["encoder2d.training"]).split(",") == ["detached", "end_to_end"]


# --------------------------------------------------------------------------- item 2: the views table is implicit


def _report_specs():
    from pcrcg.report.spec import parse_specs

    return parse_specs(OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "report.yaml").specs, resolve=True))


def test_views_table_uses_the_implicit_projection_and_explicit_is_a_second_sweep():
    for exp, proj in (("views", "implicit"), ("views_explicit", "explicit")):
        cfg = load_run_config([f"+experiment={exp}", "profile=tiny", "views=1"])
        assert cfg.experiment_name == exp and cfg.projection.name == proj and cfg.projection.views == 1
    specs = _report_specs()
    assert all(r.where["projection.name"] == "implicit" for r in specs["views"].rows)
    assert all(r.where["projection.name"] == "explicit" for r in specs["views_explicit"].rows)
    assert specs["views_explicit"].experiment == "views_explicit"


# --------------------------------------------------------------------------- item 11: Pri3D pretraining data


@pytest.mark.parametrize("profile", ["tiny", "cpu", "paper"])
def test_pri3d_pretraining_sees_other_rooms_than_the_benchmark_and_the_weights_say_so(profile):
    from conftest import compose

    from pcrcg.pretrain2d.core import _plain, default_checkpoint, pretrained_on

    pre = _plain(compose("pretrain2d", [f"profile={profile}"]))
    run = load_run_config([f"profile={profile}", "encoder2d=pri3d"], validate=False)
    # another generator seed, in a folder of its own: the benchmark's data are never touched
    assert pre["data_seed"] != run.data_seed and pre["data"]["root"] != run.data.root
    assert pre["data"]["name"] == run.data.name == "synthmatch"
    assert pretrained_on(pre) == f"synthmatch-seed{pre['data_seed']}" == run.encoder2d.pretrained_on
    # the run looks for the weights exactly where the pretraining writes them
    assert default_checkpoint(pre, Path(".")) == Path(run.encoder2d.weights)
    # real frames are named by their data set
    assert pretrained_on({"data": {"name": "redkitchen"}, "data_seed": 0}) == "redkitchen"


# --------------------------------------------------------------------------- item 3: Pri3D weights where the captions say


PRI3D_EXPERIMENTS = ("main_results", "window_size", "views", "views_explicit", "icp_init", "ransac_budget")


@pytest.mark.parametrize("experiment", PRI3D_EXPERIMENTS)
def test_the_tables_whose_captions_say_pri3d_run_with_pri3d_weights(experiment):
    cfg = load_run_config([f"+experiment={experiment}", "profile=tiny"])
    assert cfg.encoder2d.name == "pri3d" and cfg.encoder2d.make is True
    assert cfg.encoder2d.weights.endswith("pretrain2d/synthmatch-seed1-tiny/pri3d_resnet18.pth")
    if experiment != "icp_init":
        specs = _report_specs()
        tables = [s for s in specs.values() if s.experiment == experiment]
        assert tables and all(r.where.get("encoder2d.name") == "pri3d" for t in tables for r in t.rows
                              if r.where and r.where.get("label") != "Predator" and r.experiment in (None, experiment))


def test_a_run_makes_its_missing_pri3d_weights_once(tmp_path):
    from pcrcg.pretrain2d.make import make_missing_weights, pretrain_overrides
    from pcrcg.tracking.hashing import to_plain

    weights = tmp_path / "w" / "pri3d_resnet18.pth"
    data = to_plain(load_run_config(["+experiment=main_results", "profile=tiny", f"encoder2d.weights={weights}",
                                     "logger=none"], validate=False))
    ov = pretrain_overrides(data, weights)
    assert {"profile=tiny", "data=synthmatch_pretrain", "data_seed=1", f"out={weights}", "encoder2d.arch=resnet18",
            "encoder2d.out_dim=32", "logger=none", "profile.pretrain2d.steps=60"} <= set(ov)
    calls = []

    def fake_run(cmd, **kw):
        calls.append(cmd)
        weights.write_bytes(b"weights")
        return type("P", (), {"returncode": 0, "stdout": '{"match_acc_scratch": 0.1, "match_acc_pretrained": 0.2}'})()

    assert make_missing_weights(data, tmp_path, log=lambda m: None, run=fake_run) == weights
    assert calls and calls[0][1:3] == ["-m", "pcrcg.pretrain2d"]
    assert make_missing_weights(data, tmp_path, log=lambda m: None, run=fake_run) is None  # made once
    assert len(calls) == 1
    # geometry only (features=none) needs no 2D weights
    weights.unlink()
    geo = to_plain(load_run_config(["+experiment=main_results", "profile=tiny", "features=none",
                                    f"encoder2d.weights={weights}"], validate=False))
    assert make_missing_weights(geo, tmp_path, log=lambda m: None, run=fake_run) is None and len(calls) == 1
    # ... and its preflight does not ask for them (the table's geometry row runs before the color rows made them)
    preflight(geo)
    with pytest.raises(ConfigError, match="encoder2d.weights"):
        preflight(to_plain(load_run_config(["+experiment=main_results", "profile=tiny", "features=deep",
                                            f"encoder2d.weights={weights}"], validate=False)))


# --------------------------------------------------------------------------- item 12: the official training config


def test_the_official_training_config_is_a_profile_next_to_paper():
    paper = load_run_config(["profile=paper"])
    official = load_run_config(["profile=official"])
    m = official.model
    assert (m.first_dim, m.gnn_dim, m.final_dim, official.trainer.max_epochs) == (256, 512, 64, 150)
    assert (paper.model.first_dim, paper.model.gnn_dim, paper.model.final_dim, paper.trainer.max_epochs) == (
        128, 256, 32, 30)
    # everything else is the paper profile's: same voxel and levels, same data set and folder, same Pri3D file
    assert (m.voxel_size, m.num_layers) == (paper.model.voxel_size, paper.model.num_layers)
    assert official.data.root == paper.data.root and official.data.synth == paper.data.synth
    pri3d = [load_run_config([f"profile={p}", "encoder2d=pri3d"], validate=False).encoder2d.weights
             for p in ("paper", "official")]
    assert pri3d[0] == pri3d[1]


# --------------------------------------------------------------------------- item 4: the paper profile's 2D network


def test_the_paper_profiles_2d_net_is_the_official_res50_unet():
    from pcrcg.lifting import LiftingConfig
    from pcrcg.vision.encoders import build_encoder

    for profile in ("paper", "official"):
        cfg = load_run_config([f"profile={profile}", "features=deep", "projection=explicit"], validate=False)
        enc = cfg.encoder2d
        assert (enc.arch, enc.out_dim, enc.normalize, enc.output_scale) == ("resnet50", 128, False, "half")
        assert 1 + LiftingConfig.from_cfg(cfg).out_dim == 129  # the official in_feats_dim
        assert list(enc.image_size) == [240, 320] and list(cfg.projection.image_size) == [120, 160]
    net = build_encoder(OmegaConf.to_container(enc, resolve=True))
    assert net.normalize is False
    with torch.no_grad():
        out = net.eval()(torch.rand(1, 3, 64, 80))
    assert out.shape == (1, 128, 32, 40)  # 128 channels at half the input resolution
    # the small profiles keep their CPU-sized net
    small = load_run_config(["profile=cpu"]).encoder2d
    assert (small.arch, small.out_dim, small.normalize, small.output_scale) == ("resnet18", 32, True, "full")


# --------------------------------------------------------------------------- the official 2D net's BatchNorm


def test_the_2d_net_normalises_each_image_by_its_own_statistics_as_the_official_code():
    """The official 2D net stays in train mode and sees one image at a time: BatchNorm over a batch of one.
    ``bn_stats=per_image`` computes exactly that, batched, in training and at test; ``running`` is
    PyTorch's usual; pretraining uses the usual."""
    from pcrcg.vision.encoders import ResUNet, build_encoder

    torch.manual_seed(0)
    official = ResUNet("resnet18", 8, decoder_channels=[32, 16, 16, 8, 8], bn_stats="running").train()
    ours = ResUNet("resnet18", 8, decoder_channels=[32, 16, 16, 8, 8], bn_stats="per_image")
    ours.load_state_dict(official.state_dict())  # same keys and tensors: every weights file loads into both
    x = torch.rand(3, 3, 48, 64)
    with torch.no_grad():
        one_at_a_time = torch.cat([official(x[k:k + 1]) for k in range(3)])
        for mode in (True, False):
            out = ours.train(mode)(x)
            assert torch.allclose(out, one_at_a_time, atol=1e-4), mode
            assert torch.allclose(ours(x[1:2]), out[1:2], atol=1e-4)  # what a batch holds does not matter
        assert not torch.allclose(official.eval()(x), one_at_a_time, atol=1e-2)  # running averages differ
    before = [b.clone() for b in ours.buffers()]
    ours.train()(x).square().mean().backward()  # end to end: gradients reach the encoder
    assert ours.encoder.conv1.weight.grad is not None and ours.encoder.conv1.weight.grad.abs().sum() > 0
    assert all(torch.equal(a, b) for a, b in zip(before, ours.buffers()))  # running averages untouched

    assert load_run_config(["features=deep", "projection=explicit"]).encoder2d.bn_stats == "per_image"
    with pytest.raises(ConfigError, match="encoder2d.bn_stats"):
        load_run_config(["features=deep", "projection=explicit", "encoder2d.bn_stats=batch"])
    with pytest.raises(ConfigError, match="encoder2d.bn_stats"):
        build_encoder({"name": "scratch", "bn_stats": "instance"})
    # a checkpoint's lifting config from before the key: evaluated as it was trained
    assert build_encoder({"name": "scratch"}).bn_stats == "running"
    from hydra import compose, initialize_config_dir

    from pcrcg.config import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        assert compose("pretrain2d").encoder2d.bn_stats == "running"


# --------------------------------------------------------------------------- item 10: SIFT-DLT from the images


def _corner_view(pose, planes, H=120, W=160):
    """A camera (pose camera-to-fragment) in a room corner: the nearest of ``planes`` (n.p = d, fragment
    frame) in front of each pixel gives its depth (a non-planar scene, as an essential matrix needs)."""
    from pcrcg.data.dataset import View

    K = np.array([[150.0, 0, W / 2 - 0.5], [0, 150.0, H / 2 - 0.5], [0, 0, 1]])
    R, t = pose[:3, :3], pose[:3, 3]
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    z = np.full((H, W), np.inf)
    for n, d in planes:
        n_c, d_c = R.T @ n, d - n @ t
        zi = d_c / (rays @ n_c)
        z = np.where((zi > 0.1) & (zi < z), zi, z)
    depth = np.where(np.isfinite(z) & (z < 6.0), z, 0.0).astype(np.float32)
    return View(np.zeros((H, W, 3), np.uint8), depth, K, pose, 0, "corner.png")


def test_sift_dlt_is_a_relative_pose_from_the_images_with_scale_from_depth():
    from pcrcg.geometry import axis_angle_to_matrix, invert, make_transform, project, transform_points
    from pcrcg.registration import BaselineConfig, lift_pixels, register_pair
    from pcrcg.vision.matching import Matches

    rng = np.random.default_rng(3)
    # a room seen from inside: back wall 2.5 m ahead, side walls, the floor
    planes = [(np.array([0.0, 0.0, 1.0]), 2.5), (np.array([1.0, 0.0, 0.0]), 0.8), (np.array([0.0, 1.0, 0.0]), 0.6),
              (np.array([-1.0, 0.0, 0.0]), 0.9)]
    T = make_transform(axis_angle_to_matrix([0.1, 1.0, 0.2], 0.15), [0.25, -0.05, 0.1])  # src frag -> tgt frag
    src_pose = make_transform(axis_angle_to_matrix([0, 1, 0], 0.1), [0.1, 0.0, 0.0])
    tgt_pose = make_transform(axis_angle_to_matrix([1, 0, 0], 0.05), [0.0, 0.05, 0.0])
    src_view = _corner_view(src_pose, planes)
    inv = invert(T)
    tgt_planes = [(T[:3, :3] @ n, d + (T[:3, :3] @ n) @ T[:3, 3]) for n, d in planes]  # the scene, tgt frame
    tgt_view = _corner_view(tgt_pose, tgt_planes)
    assert np.allclose(inv @ T, np.eye(4))

    def fake_match(img_a, img_b):
        uv_a = rng.uniform([0, 10], [159, 119], size=(800, 2))
        pa, ok = lift_pixels(uv_a, src_view)
        uv_b, z = project(transform_points(invert(tgt_view.pose), transform_points(T, pa[ok])), tgt_view.intrinsics)
        keep = (z > 0) & (uv_b[:, 0] >= 0) & (uv_b[:, 0] < 160) & (uv_b[:, 1] >= 0) & (uv_b[:, 1] < 120)
        ua, ub = uv_a[ok][keep], uv_b[keep] + rng.normal(scale=0.2, size=(int(keep.sum()), 2))
        ub[: len(ub) // 4] = rng.uniform([0, 0], [159, 119], size=(len(ub) // 4, 2))  # outliers
        return Matches(ua, ub, np.ones(len(ub), np.float32))

    from pcrcg.registration.baselines import register_sift_dlt

    res = register_sift_dlt([src_view], [tgt_view], BaselineConfig(), seed=0, matcher=fake_match)
    r = np.degrees(np.arccos(np.clip((np.trace(res.transform[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1)))
    t = float(np.linalg.norm(res.transform[:3, 3] - T[:3, 3]))
    assert r < 1.0 and t < 0.03, (r, t)  # the metric translation: its scale came from depth
    assert res.info["n_inliers"] > 300 and res.info["view_pair"] == (0, 0)
    # no image pose (too few matches): the identity, as the paper's 0.4% recall suggests happens often
    few = register_sift_dlt([src_view], [tgt_view], BaselineConfig(), matcher=lambda a, b: Matches(
        np.zeros((3, 2)), np.zeros((3, 2)), np.ones(3)))
    assert np.array_equal(few.transform, np.eye(4))
    # the former reading (3D RANSAC on depth-lifted matches) is kept under its own name
    cfg = load_run_config(["profile=tiny", "method=sift_lifted"])
    assert cfg.method == "sift_lifted" and "distance" in cfg.registration.sift_lifted
    assert "threshold" in cfg.registration.sift_dlt and "distance" not in cfg.registration.sift_dlt
    with pytest.raises(ValueError, match="views"):
        register_pair("sift_dlt", None, None, src_views=[], tgt_views=[tgt_view])


def test_sift_dlt_on_real_kinect_frames():
    from conftest import shared_path

    from pcrcg.data.dataset import View
    from pcrcg.data.layout import read_color, read_depth, read_intrinsics, read_pose
    from pcrcg.evaluation.metrics import rotation_error_deg
    from pcrcg.geometry import invert
    from pcrcg.registration import BaselineConfig, register_pair

    frames = shared_path("data", "real-rgbd", "redkitchen-frames")
    K = read_intrinsics(frames / "camera-intrinsics.txt")

    def view(k):  # frame k as the first view of a fragment in its own camera frame
        color = frames / f"frame-{k:06d}.color.png"
        return View(read_color(color), read_depth(frames / f"frame-{k:06d}.depth.png"), K, np.eye(4), k, str(color))

    T = invert(read_pose(frames / "frame-000040.pose.txt")) @ read_pose(frames / "frame-000008.pose.txt")
    cfg = BaselineConfig.from_dict({"sift_dlt": {"matcher": {"method": "sift", "max_keypoints": 1500}}})
    res = register_pair("sift_dlt", None, None, src_views=[view(8)], tgt_views=[view(40)], cfg=cfg, seed=0)
    assert rotation_error_deg(res.transform[:3, :3], T[:3, :3]) < 3.0
    assert np.linalg.norm(res.transform[:3, 3] - T[:3, 3]) < 0.05  # metric: the scale came from depth


# --------------------------------------------------------------------------- the report names what differs


def test_the_report_names_per_table_the_settings_that_differ_from_the_paper_and_its_code():
    import pandas as pd

    from pcrcg.report.fidelity import fidelity_lines
    from pcrcg.report.render import to_markdown
    from pcrcg.report.tables import fill_table, load_paper

    base = {"run_id": "r1", "experiment": "backbone_2d", "status": "FINISHED", "start_time": pd.Timestamp(0),
            "tags.profile": "cpu", "params.seed": "0", "params.method": "learned", "params.features.name": "deep",
            "params.projection.name": "explicit", "params.encoder2d.name": "scratch", "params.encoder2d.arch": "resnet18",
            "params.encoder2d.out_dim": "32", "params.encoder2d.normalize": "True", "params.matcher2d.method": "sift",
            "params.projection.combine": "overwrite", "params.projection.unseen_value": "1.0",
            "params.model.loss.log_scale": "16", "params.registration.fewer_points": "with_replacement",
            "params.registration.ransac.max_validation": "1000", "params.encoder2d.training": "detached",
            "metrics.3DLoMatch/rr_5000": 50.0}
    runs = pd.DataFrame([base, {**base, "run_id": "r2", "params.encoder2d.training": "end_to_end",
                                "params.registration.ransac.max_validation": "null"}])
    text = " | ".join(fidelity_lines(runs))
    assert "the 2D network detached (not trained) (1 runs); the 2D network trained end to end (1 runs)" in text
    assert "RANSAC stops after 1000 validated hypotheses" in text and "Open3D >= 0.12's budget" in text
    assert "profile cpu" in text and "the official code: profile official" in text
    assert "2D matches from SIFT" in text and "SuperGlue" in text and "2D encoder resnet18" in text
    # as the code but not the text: said so; as both (or as the code where the text says nothing): not listed
    assert "the first that sees a point gives its feature (as the official code, the paper's text: several views: " \
           "features averaged)" in text
    assert "circle-loss" not in text and "small fragments" not in text and "points no view sees" not in text
    # runs logged before encoder2d.bn_stats existed ran with PyTorch's usual statistics, and are said to
    assert "2D BatchNorm with batch statistics in training and running averages at test (the official code: " \
           "2D BatchNorm normalising each image by its own statistics)" in text
    per_image = runs.assign(**{"params.encoder2d.bn_stats": "per_image"})
    assert "BatchNorm" not in " | ".join(fidelity_lines(per_image))
    # explicit windows: runs logged before projection.window_style drew them centred (the paper's text), not as
    # the official code's slices; an official-style run is as the code, not as the text
    assert "explicit windows of window_size x window_size pixels centred on the matches (the official code: " \
           "explicit windows as the official code's slices (2 * ((window_size - 1) // 2) pixels wide, later matches " \
           "overwriting, none past the top or left border), as the paper's text)" in text
    official = runs.assign(**{"params.projection.window_style": "official"})
    assert "none past the top or left border) (as the official code, the paper's text: explicit windows of " \
           "window_size x window_size pixels centred on the matches)" in " | ".join(fidelity_lines(official))
    # ... and the table says them under its cells
    spec = _report_specs()["backbone_2d"]
    table = fill_table(spec, runs, load_paper(), {"backbone_2d": "cpu"})
    assert table.fidelity and "Settings of these runs that differ from the paper's text or its official code" in \
        to_markdown(table)
