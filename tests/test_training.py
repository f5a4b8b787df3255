"""End-to-end training in Lightning on tiny synthetic data made here: the loss goes down, checkpoints
round-trip, an interrupted run resumes, inference outputs the registration stage's arrays, and the
color branch plugs in through the first layer's width only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import lightning as L
from lightning.pytorch.callbacks import Callback

from pcrcg.errors import ConfigError, DataError
from pcrcg.data.layout import PairRecord, write_gt_log, write_pairs, write_ply
from pcrcg.models.datamodule import EpochSampler, PairCollate, PairDataModule
from pcrcg.models.kpconv import PyramidSpec, calibrate_limits
from pcrcg.models.module import PCRCGModule
from pcrcg.testing.pairs import toy_pair
from pcrcg.models.train import infer, infer_clouds, load_module, load_pair_output, save_pair_output, train

VOXEL, DENSITY = 0.15, 100.0
MODEL = dict(name="predator", voxel_size=VOXEL, num_layers=3, first_dim=16, final_dim=16, gnn_dim=16, num_heads=2,
             dgcnn_k=6, max_points=3000, loss=dict(matchability_after_recall=0.0))


def trainer_cfg(**kw):
    base = dict(accelerator="cpu", max_epochs=5, max_steps=2, limit_val_batches=1, log_every_n_steps=1,
                checkpoint_every_n_steps=1, num_workers=0, progress_bar=False, csv_logger=True,
                optim=dict(lr=0.005, momentum=0.98, weight_decay=1e-6, lr_decay=0.95),
                augment=dict(enabled=True, rotation_range_deg=360, noise_std=0.0015))
    base.update(kw)
    return base


def write_toy_layout(root: Path, n_pairs: int = 2) -> Path:
    """A data set in the 3DMatch layout: toy pairs as fragments 0/1 of scenes toy<k>, train and val."""
    records = []
    for k in range(n_pairs):
        s = toy_pair(k, density=DENSITY)
        d = root / "fragments" / s.scene
        d.mkdir(parents=True, exist_ok=True)
        write_ply(d / f"cloud_bin_{s.i}.ply", s.tgt_points)
        write_ply(d / f"cloud_bin_{s.j}.ply", s.src_points)
        records.append(PairRecord(s.scene, s.i, s.j, s.transform, s.overlap, n_fragments=2))
        bench = root / "benchmarks" / "3DMatch" / s.scene
        bench.mkdir(parents=True, exist_ok=True)
        write_gt_log(bench / "gt.log", records[-1:])
    (root / "pairs").mkdir(parents=True, exist_ok=True)
    write_pairs(root / "pairs" / "train.txt", records)
    write_pairs(root / "pairs" / "val.txt", records[:1])
    return root


@pytest.fixture(scope="module")
def toy_root(tmp_path_factory) -> Path:
    return write_toy_layout(tmp_path_factory.mktemp("toydata"))


def fixed_batch(seed: int = 0):
    s = toy_pair(seed, density=DENSITY)
    spec = PyramidSpec(VOXEL, 3, 2.5)
    spec = PyramidSpec(VOXEL, 3, 2.5, calibrate_limits([s.src_points, s.tgt_points], spec))
    return PairCollate(spec, overlap_radius=1.5 * VOXEL)([s])


def test_a_few_steps_lower_the_loss():
    torch.manual_seed(0)
    batch = fixed_batch()
    module = PCRCGModule(MODEL)
    assert module.in_dim == 1 and module.lifter is None  # geometry only
    opt = module.configure_optimizers()["optimizer"]
    assert opt.defaults["lr"] == 0.005 and opt.defaults["momentum"] == 0.98
    losses = []
    for _ in range(8):
        out, _ = module(batch)
        stats = module.compute_stats(batch, out)
        opt.zero_grad()
        stats["loss"].backward()
        opt.step()
        losses.append(float(stats["loss"].detach()))
    assert np.mean(losses[-3:]) < 0.9 * np.mean(losses[:3]), losses


def test_adam_option_and_unknown_optimiser():
    module = PCRCGModule(MODEL, optim={"name": "adam", "lr": 1e-3})
    opt = module.configure_optimizers()["optimizer"]
    assert isinstance(opt, torch.optim.Adam) and opt.defaults["lr"] == 1e-3
    with pytest.raises(ValueError, match="trainer.optim.name='lamb'"):
        PCRCGModule(MODEL, optim={"name": "lamb"})


def test_cosine_schedule_warms_up_then_falls_to_zero_over_the_run_steps():
    from pcrcg.models.module import cosine_factor

    assert [cosine_factor(s, 10, warmup=4) for s in range(4)] == [0.25, 0.5, 0.75, 1.0]
    assert cosine_factor(4, 10, warmup=4) == 1.0 and cosine_factor(7, 10, warmup=4) == pytest.approx(0.5)
    assert cosine_factor(10, 10, warmup=4) == pytest.approx(0.0, abs=1e-12) == cosine_factor(12, 10, warmup=4)
    assert cosine_factor(0, 8) == 1.0 and cosine_factor(2, 8) == pytest.approx((1 + np.cos(np.pi / 4)) / 2)
    with pytest.raises(ValueError, match="trainer.optim.schedule='linear'"):
        PCRCGModule(MODEL, optim={"schedule": "linear"})
    with pytest.raises(ValueError, match="trainer.optim.warmup_steps=-2"):
        PCRCGModule(MODEL, optim={"schedule": "cosine", "warmup_steps": -2})


def test_a_cosine_run_steps_its_learning_rate_every_step_as_the_formula(tmp_path, toy_root):
    """Through Lightning (3 epochs of 2 steps): the rate of every step is lr x cosine_factor(step, 6, 2), and
    the exponential schedule, the default, still steps once an epoch."""
    from pcrcg.models.module import cosine_factor

    seen = []

    class Rates(Callback):
        def on_train_batch_start(self, trainer, *args):
            seen.append(trainer.optimizers[0].param_groups[0]["lr"])

    for schedule in ("cosine", "exponential"):
        seen.clear()
        cfg = trainer_cfg(max_epochs=3, max_steps=None, limit_train_batches=2, limit_val_batches=0,
                          optim=dict(name="adam", lr=0.01, schedule=schedule, warmup_steps=2, lr_decay=0.5))
        train({"model": MODEL, "trainer": cfg, "seed": 0, "data": {"root": str(toy_root)}}, out_dir=tmp_path / schedule,
              callbacks=[Rates()])
        if schedule == "cosine":
            assert seen == pytest.approx([0.01 * cosine_factor(s, 6, 2) for s in range(6)])
        else:
            assert seen == pytest.approx([0.01, 0.01, 0.005, 0.005, 0.0025, 0.0025])


class CountSteps(Callback):
    """Counts training steps; raises at the end of step ``fail_at`` (or, ``before=True``, as the step after
    it starts)."""

    def __init__(self, fail_at: int | None = None, before: bool = False):
        self.steps = 0
        self.fail_at = fail_at
        self.before = before

    def on_train_batch_start(self, trainer, *args):
        if self.before and trainer.global_step == self.fail_at:
            raise RuntimeError("simulated crash")

    def on_train_batch_end(self, trainer, *args):
        self.steps += 1
        if not self.before and self.fail_at is not None and trainer.global_step == self.fail_at:
            raise RuntimeError("simulated crash")


def test_interrupted_training_resumes_from_last_checkpoint(tmp_path, toy_root3, monkeypatch):
    saves = []
    real_save = L.Trainer.save_checkpoint

    def spy(self, filepath, weights_only=None, storage_options=None):
        saves.append(weights_only)
        return real_save(self, filepath, weights_only=weights_only, storage_options=storage_options)

    monkeypatch.setattr(L.Trainer, "save_checkpoint", spy)
    # no periodic checkpoint before the crash: last.ckpt must come from the crash itself
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=4, checkpoint_every_n_steps=100), "seed": 0,
           "data": {"root": str(toy_root3)}}
    out_dir = tmp_path / "run"
    first = CountSteps(fail_at=2)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg, out_dir=out_dir, callbacks=[first])
    last = out_dir / "checkpoints" / "last.ckpt"
    assert last.is_file() and first.steps == 2
    assert saves and all(w is False for w in saves)  # the full state, said explicitly (no log line per save)
    ck = torch.load(last, map_location="cpu", weights_only=False)
    assert ck["global_step"] == 2 and ck["optimizer_states"][0]["state"]  # momentum buffers saved
    spent = ck["callbacks"]["TrainingClock"]  # the seconds of the start that wrote it, up to then
    assert spent["wall_s"] > 0 and spent["cpu_s"] > 0
    assert len(ck["hyper_parameters"]["model"]["neighbor_limits"]) == 3
    assert list((out_dir / "logs").glob("version_0/metrics.csv"))  # curves from a 2-step run
    w_before = ck["state_dict"]["net.encoder.0.conv.weights"]

    # the same call again: resumes from last.ckpt and runs only the missing steps
    second = CountSteps()
    res = train(cfg, out_dir=out_dir, callbacks=[second])
    assert second.steps == 2
    assert res["metrics"]["train/global_step"] == 4 and res["metrics"]["train/resumed_from_step"] == 2, res["metrics"]
    # what the first start spent up to its checkpoint, for the run's time (time/train_s counts this start only)
    assert res["metrics"]["time/train_earlier_s"] == pytest.approx(spent["wall_s"])
    assert res["metrics"]["time/train_earlier_cpu_s"] == pytest.approx(spent["cpu_s"])
    assert any(k.startswith("train/loss") for k in res["history"])
    ck2 = torch.load(res["last_checkpoint"], map_location="cpu", weights_only=False)
    assert ck2["global_step"] == 4 and ck2["epoch"] >= ck["epoch"]
    assert ck2["callbacks"]["TrainingClock"]["wall_s"] > spent["wall_s"]  # both starts' seconds
    assert not torch.equal(ck2["state_dict"]["net.encoder.0.conv.weights"], w_before)
    assert list((out_dir / "logs").glob("version_1/metrics.csv"))  # the first curves are kept
    # a finished run called again does nothing more
    third = CountSteps()
    train(cfg, out_dir=out_dir, callbacks=[third])
    assert third.steps == 0


@pytest.fixture(scope="module")
def toy_root3(tmp_path_factory) -> Path:
    return write_toy_layout(tmp_path_factory.mktemp("toydata3"), n_pairs=3)


def _final_state(out_dir: Path) -> dict:
    ck = torch.load(out_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ck["global_step"] == 7
    return ck


@pytest.mark.parametrize("crash_at, before, every, resumed_at, workers", [
    (2, False, 100, 2, 0), (3, False, 1, 2, 0), (3, True, 100, 3, 0),
    pytest.param(3, True, 100, 3, 2, marks=pytest.mark.slow)],
    ids=["mid-epoch", "before-validation", "epoch-end", "epoch-end-2-loader-processes"])
def test_a_resumed_training_is_bit_for_bit_the_uninterrupted_one(tmp_path, toy_root3, crash_at, before, every,
                                                                  resumed_at, workers):
    """3 pairs an epoch, 7 steps (epochs 0, 1 and one step of 2), augmentation on. Crashed after step 2 (mid
    epoch: saved there), after step 3 (the epoch's last batch, its validation due: nothing is saved there, the
    run resumes from step 2's periodic save) or as step 4 starts (resumes from epoch 0's end), the resumed
    run's weights, optimiser state and validation curve are the uninterrupted run's. With loader processes
    (the interrupted run's only), whose iterators start drawing indices as soon as they exist."""
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=7, max_epochs=10, checkpoint_every_n_steps=every),
           "seed": 3, "data": {"root": str(toy_root3)}}
    train(cfg, out_dir=tmp_path / "whole")
    cfg["trainer"]["num_workers"] = workers
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg, out_dir=tmp_path / "cut", callbacks=[CountSteps(fail_at=crash_at, before=before)])
    ck = torch.load(tmp_path / "cut" / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert ck["global_step"] == resumed_at
    rest = CountSteps()
    res = train(cfg, out_dir=tmp_path / "cut", callbacks=[rest])
    assert rest.steps == 7 - resumed_at and res["metrics"]["train/resumed_from_step"] == resumed_at
    a, b = _final_state(tmp_path / "whole"), _final_state(tmp_path / "cut")
    differ = [k for k in a["state_dict"] if not torch.equal(a["state_dict"][k], b["state_dict"][k])]
    assert not differ, f"{len(differ)} of {len(a['state_dict'])} tensors differ, e.g. {differ[:3]}"
    for sa, sb in zip(a["optimizer_states"][0]["state"].values(), b["optimizer_states"][0]["state"].values()):
        assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a["epoch"] == b["epoch"]
    best = [torch.load(d / "checkpoints" / "best.ckpt", map_location="cpu", weights_only=True)
            for d in (tmp_path / "whole", tmp_path / "cut")]
    assert best[0]["global_step"] == best[1]["global_step"]
    assert all(torch.equal(best[0]["state_dict"][k], best[1]["state_dict"][k]) for k in best[0]["state_dict"])


@pytest.mark.slow
def test_a_resumed_pcr_cg_training_is_bit_for_bit_the_uninterrupted_one(tmp_path, tiny_root):
    """The same with color: deep features of a 2D encoder trained with the 3D network (its batch norms in
    training mode), explicit projection on SIFT matches, the tiny profile's data and 6 steps over 2 epochs."""
    from omegaconf import OmegaConf

    from conftest import compose

    cfg = compose("run", ["profile=tiny", f"data.root={tiny_root}", "features=deep", "projection=explicit",
                          "encoder2d=scratch", "matcher2d=sift", "trainer.max_steps=6", "trainer.max_epochs=2",
                          "trainer.limit_train_batches=3", "trainer.limit_val_batches=1",
                          "trainer.checkpoint_every_n_steps=100", "trainer.progress_bar=false", "seed=2"])
    OmegaConf.set_struct(cfg, False)
    train(cfg, out_dir=tmp_path / "whole", logger=False)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg, out_dir=tmp_path / "cut", logger=False, callbacks=[CountSteps(fail_at=2)])
    rest = CountSteps()
    res = train(cfg, out_dir=tmp_path / "cut", logger=False, callbacks=[rest])
    assert rest.steps == 4 and res["metrics"]["train/resumed_from_step"] == 2
    a, b = (torch.load(d / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)["state_dict"]
            for d in (tmp_path / "whole", tmp_path / "cut"))
    assert any(k.startswith("lifter.") for k in a)  # the 2D encoder is in it
    differ = [k for k in a if not torch.equal(a[k], b[k])]
    assert not differ, f"{len(differ)} of {len(a)} tensors differ, e.g. {differ[:3]}"


@pytest.mark.slow
def test_loader_processes_change_no_result(tmp_path, toy_root3):
    """The augmentations come from the sampler, not from the loader processes: 2 workers train the same weights."""
    states = []
    for workers in (0, 2):
        cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=4, max_epochs=10, num_workers=workers), "seed": 1,
               "data": {"root": str(toy_root3)}}
        res = train(cfg, out_dir=tmp_path / f"w{workers}")
        states.append(torch.load(res["last_checkpoint"], map_location="cpu", weights_only=True)["state_dict"])
    assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])


def test_the_epoch_sampler_is_a_function_of_seed_epoch_and_rank_alone():
    torch.manual_seed(0)
    before = torch.get_rng_state()
    one = EpochSampler(range(10), seed=5)
    e0, e1 = list(one), list(one)  # an epoch per iteration
    assert torch.equal(torch.get_rng_state(), before)  # no global random state read or advanced
    assert sorted(i for i, _ in e0) == list(range(10)) and [i for i, _ in e0] != [i for i, _ in e1]
    assert len({seed for _, seed in e0 + e1}) == 20  # each (epoch, position) its own augmentation seed
    assert list(EpochSampler(range(10), seed=5)) == e0 and list(EpochSampler(range(10), seed=6)) != e0
    # sharded over 2 ranks: disjoint halves that together are the epoch
    halves = [list(EpochSampler(range(10), seed=5, num_replicas=2, rank=r)) for r in (0, 1)]
    assert sorted(i for h in halves for i, _ in h) == list(range(10))
    # resumed at epoch 1 after 4 items: the rest of epoch 1, then epoch 2; at an epoch's end: the next epoch
    again = EpochSampler(range(10), seed=5)
    again.load_state_dict({"epoch": 1, "done": 4, "epoch_batches": 10})
    assert list(again) == e1[4:] and again.state_dict()["epoch"] == 1
    fresh = EpochSampler(range(10), seed=5)
    e2 = [list(fresh) for _ in range(3)][-1]
    assert list(again) == e2
    ended = EpochSampler(range(10), seed=5)
    ended.load_state_dict({"epoch": 0, "done": 10, "epoch_batches": 10})
    assert list(ended) == e1
    ended.set_epoch(7)  # Lightning's number is not the sampler's
    assert list(ended) == e2


def test_best_checkpoint_round_trip_and_inference(tmp_path, toy_root):
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=2, max_epochs=1, limit_train_batches=2),
           "data": {"root": str(toy_root)}}
    res = train(cfg, out_dir=tmp_path / "run")
    best = Path(res["checkpoint"])
    assert best.name == "best.ckpt" and best.is_file()
    assert "best/val/circle_loss" in res["metrics"]

    module = load_module(best, device="cpu")
    again = load_module(best, device="cpu")
    outs = list(infer(module, toy_root, "val", progress=False))
    assert len(outs) == 1
    o = outs[0]
    for frag in (o.src, o.tgt):
        n = len(frag.points)
        assert frag.descriptors.shape == (n, 16) and frag.overlap.shape == (n,) and frag.matchability.shape == (n,)
        np.testing.assert_allclose(np.linalg.norm(frag.descriptors, axis=1), 1.0, atol=1e-5)
        assert frag.points.dtype == np.float32
    # outputs are in the fragments' own frames: the stored ground truth maps src onto tgt
    s = toy_pair(0, density=DENSITY)
    np.testing.assert_allclose(o.transform, s.transform, atol=1e-5)
    # a reloaded checkpoint gives the same numbers (deterministic inference)
    o2 = next(infer(again, toy_root, "val", progress=False))
    np.testing.assert_allclose(o.src.descriptors, o2.src.descriptors, atol=1e-5)
    # the evaluation stage's hook, on a test benchmark
    from pcrcg.models.predict import predict_benchmark

    bench = list(predict_benchmark(None, toy_root, best, "3DMatch", device="cpu", progress=False))
    assert [(b.scene, b.i, b.j) for b in bench] == [("toy0", 0, 1), ("toy1", 0, 1)]
    np.testing.assert_allclose(bench[0].tgt.descriptors, o.tgt.descriptors, atol=1e-5)
    # with trainer.cache_dir the test pyramids are kept on disk, and read back as they were built
    kept = tmp_path / "pyramids"
    for _ in range(2):
        cached = list(predict_benchmark({"trainer": {"cache_dir": str(kept)}}, toy_root, best, "3DMatch",
                                        device="cpu", progress=False))
        assert len(list(kept.glob("pyr_*.npz"))) == 4  # two pairs of two fragments
        for b, c in zip(bench, cached):
            np.testing.assert_array_equal(b.src.descriptors, c.src.descriptors)
    # user clouds, and the .npz hand-over to the registration stage
    oc = infer_clouds(module, s.src_points, s.tgt_points)
    np.testing.assert_allclose(oc.src.descriptors, o.src.descriptors, atol=1e-5)
    path = save_pair_output(o, tmp_path / "pair.npz")
    back = load_pair_output(path)
    np.testing.assert_array_equal(back.tgt.descriptors, o.tgt.descriptors)
    assert (back.scene, back.i, back.j) == (o.scene, o.i, o.j)
    # the same from the command line: `python -m pcrcg.evaluate mode=pair method=learned checkpoint=...`
    from hydra import compose, initialize_config_dir

    from pcrcg.evaluate import run as evaluate_run

    write_ply(tmp_path / "src.ply", s.src_points)
    write_ply(tmp_path / "tgt.ply", s.tgt_points)
    args = ["profile=tiny", "mode=pair", "method=learned", f"source={tmp_path / 'src.ply'}",
            f"target={tmp_path / 'tgt.ply'}", "pair_points=500"]
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "conf"), version_base="1.3"):
        res = evaluate_run(compose(config_name="evaluate", overrides=[*args, f"checkpoint={best}"]))
        with pytest.raises(DataError, match="none.ckpt"):
            evaluate_run(compose(config_name="evaluate", overrides=[*args, f"checkpoint={tmp_path / 'none.ckpt'}"]))
    T = np.asarray(res["transform"])
    assert T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
    assert res["points"] == [len(o.src.points), len(o.tgt.points)] and res["correspondences"] > 0


def test_training_on_a_data_set_without_training_pairs_is_one_line(tmp_path):
    """A test-only data set (the real 3DMatch scene's layout: an empty pairs/train.txt) is a DataError naming that
    file when training is set up, not a sampler's ValueError from inside Lightning."""
    (tmp_path / "pairs").mkdir()
    write_pairs(tmp_path / "pairs" / "train.txt", [])
    dm = PairDataModule(tmp_path, voxel_size=VOXEL, num_layers=3)
    with pytest.raises(DataError, match=r"pairs/train.txt: no training pairs"):
        dm.setup("fit")


def test_datamodule_calibrates_and_restores_limits(toy_root):
    dm = PairDataModule(toy_root, voxel_size=VOXEL, num_layers=3)
    dm.setup("fit")
    assert dm.limits is not None and len(dm.limits) == 3
    other = PairDataModule(toy_root, voxel_size=VOXEL, num_layers=3)
    other.load_state_dict(dm.state_dict())
    assert other.limits == dm.limits
    batch = next(iter(dm.train_dataloader()))
    assert batch.corr.shape[1] == 2 and len(batch.corr) > 0
    # the augmented transform still maps the augmented source onto the target
    ns = batch.n_src
    p = batch.pyramid.points[0].double()
    src = p[:ns] @ batch.transform[:3, :3].double().T + batch.transform[:3, 3].double()
    d = (src[batch.corr[:, 0]] - p[ns:][batch.corr[:, 1]]).norm(dim=1)
    assert float(d.max()) < 1.5 * VOXEL + 0.02  # overlap radius + augmentation noise


# --------------------------------------------------------------------------- color branch


def _lifting(projection: str, features: str, **feat):
    return {"projection": {"name": projection, "views": 2, "window_size": 11, "depth_tolerance": 0.1},
            "features": {"name": features, **feat}}


@pytest.fixture(scope="module")
def color_pair():
    from pcrcg.testing import scenes  # first-party: an ImportError must fail, not skip

    return scenes.make_pair(0, width=80, height=60, frames=3, voxel=0.05)


def _color_batch(sample, voxel=0.1):
    spec = PyramidSpec(voxel, 3, 2.5)
    spec = PyramidSpec(voxel, 3, 2.5, calibrate_limits([sample.src_points, sample.tgt_points], spec))
    from pcrcg.models.datamodule import AugmentConfig

    return PairCollate(spec, overlap_radius=1.5 * voxel, augment=AugmentConfig())([sample])


def test_rgb_lifting_widens_only_the_input(color_pair):
    model = {**MODEL, "voxel_size": 0.1}
    module = PCRCGModule(model, lifting=_lifting("implicit", "rgb", dim=3))
    assert module.in_dim == 4
    batch = _color_batch(color_pair)
    feats, coverage = module.input_features(batch)
    assert feats.shape == (batch.pyramid.points[0].shape[0], 4)
    assert torch.all(feats[:, 0] == 1.0)
    assert 0.3 < coverage <= 1.0
    # lifted in the fragments' own frames: the same features with and without augmentation
    plain = PairCollate(PyramidSpec(0.1, 3, 2.5, (40, 40, 40)), 0.15)([color_pair])
    f2, _ = module.input_features(plain)
    torch.testing.assert_close(feats, f2)
    loss = module.training_step(batch, 0)
    assert loss is not None and torch.isfinite(loss)


def test_deep_features_train_the_2d_encoder(color_pair):
    import pcrcg.vision.encoders  # noqa: F401  (first-party: an ImportError must fail, not skip)

    model = {**MODEL, "voxel_size": 0.1}
    lifting = {**_lifting("implicit", "deep", dim=8),
               "encoder2d": {"name": "scratch", "arch": "resnet18", "out_dim": 8, "weights": None,
                             "image_size": [48, 64]}}
    torch.manual_seed(0)
    module = PCRCGModule(model, lifting=lifting)
    assert module.in_dim == 9
    batch = _color_batch(color_pair)
    loss = module.training_step(batch, 0)
    loss.backward()
    enc_grads = [p.grad for p in module.lifter.parameters() if p.grad is not None]
    assert enc_grads and sum(float(g.abs().sum()) for g in enc_grads) > 0  # the 3D loss reaches the 2D encoder
    groups = module.configure_optimizers()["optimizer"].param_groups
    assert len(groups) == 2  # 3D network and 2D branch


@pytest.mark.slow
def test_ddp_spawn_on_two_cpu_processes(tmp_path, toy_root):
    # the trainer=ddp path (strategy passed through to Lightning) on 2 CPU processes (gloo): both
    # processes step, rank 0 writes the checkpoints, and the result is returned to the caller
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=2, devices=2, strategy="ddp_spawn", limit_val_batches=1),
           "seed": 0, "data": {"root": str(toy_root)}}
    res = train(cfg, out_dir=tmp_path / "ddp")
    ck = torch.load(res["last_checkpoint"], map_location="cpu", weights_only=False)
    assert ck["global_step"] == 2
    module = load_module(res["checkpoint"])
    saved = torch.load(res["checkpoint"], map_location="cpu", weights_only=True)["state_dict"]
    for k, v in module.state_dict().items():  # the weights rank 0 wrote are the ones read back
        assert torch.equal(v, saved[k]), k


def test_the_matchability_loss_is_on_as_each_official_trainer_has_it():
    """``model.loss.matchability_after_recall: official`` (the default): geometry only, Predator's schedule (off until
    a validation recall above 0.3, off again below it); with lifted 2D features, PCR-CG's trainer (on from the first
    step, whatever the recall); a number is that threshold for every run; anything else names the setting."""
    base = {**MODEL, "voxel_size": 0.1, "loss": {}}

    def validate(module, recall):
        module.on_validation_epoch_start()
        module._val_recalls.append(recall)
        module.on_validation_epoch_end()
        return float(module.matchability_gate)

    geometry = PCRCGModule(base)
    assert geometry.loss_cfg.matchability_after_recall == "official" and geometry.matchability_after == 0.3
    assert float(geometry.matchability_gate) == 0.0
    assert [validate(geometry, r) for r in (0.2, 0.35, 0.25)] == [0.0, 1.0, 0.0]
    color = PCRCGModule(base, lifting=_lifting("implicit", "rgb", dim=3))
    assert color.matchability_after == 0.0 and float(color.matchability_gate) == 1.0
    assert [validate(color, r) for r in (0.1, 0.05)] == [1.0, 1.0]
    schedule = PCRCGModule({**base, "loss": {"matchability_after_recall": 0.3}}, lifting=_lifting("implicit", "rgb", dim=3))
    assert float(schedule.matchability_gate) == 0.0 and [validate(schedule, r) for r in (0.2, 0.4)] == [0.0, 1.0]
    with pytest.raises(ConfigError, match="model.loss.matchability_after_recall"):
        PCRCGModule({**base, "loss": {"matchability_after_recall": "predator"}})


def test_the_training_clock_reads_what_a_checkpoint_holds():
    """The seconds a checkpoint holds come back as the earlier starts'; a value that is not a non-negative number
    (a damaged or hand-edited checkpoint) counts as none rather than stopping the resumed run."""
    from pcrcg.models.train import TrainingClock

    clock = TrainingClock()
    assert clock.earlier() == (0.0, 0.0) and clock.state_dict() == {"wall_s": 0.0, "cpu_s": 0.0}
    assert not clock.restored  # a checkpoint without the clock (older code): its run logs no earlier seconds
    clock.load_state_dict({"wall_s": 12.5, "cpu_s": 10})
    assert clock.restored
    assert clock.earlier() == (12.5, 10.0) and clock.state_dict() == {"wall_s": 12.5, "cpu_s": 10.0}
    clock.load_state_dict({"wall_s": "soon", "cpu_s": float("nan")})
    assert clock.earlier() == (0.0, 0.0)
    clock.load_state_dict({"wall_s": -3.0})
    assert clock.earlier() == (0.0, 0.0)
