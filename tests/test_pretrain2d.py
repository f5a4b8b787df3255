"""2D pretraining (Pri3D-style): correspondences on a ray-cast scene with known geometry, the InfoNCE
loss and the matching metric on hand-made features, training on a small RGB-D data set made here,
and the checkpoint loading into a run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from pcrcg.data.layout import Layout, frame_paths, write_color, write_depth, write_matrix, write_split
from pcrcg.errors import ConfigError, DataError
from pcrcg.geometry import backproject, invert, look_at, project, transform_points
from pcrcg.testing.scenes import ToyRoom, pan_path, render, toy_intrinsics
from pcrcg.vision.pretrain import (
    color_jitter,
    crop_pair,
    gather_pixels,
    info_nce,
    match_accuracy,
    overlap_ratio,
    pixel_correspondences,
    relative_pose,
    resize_view,
    sample_matches,
    select_view_pairs,
)

REPO = Path(__file__).resolve().parents[1]
W, H = 80, 60


# --------------------------------------------------------------------------- correspondences


@pytest.fixture(scope="module")
def room():
    return ToyRoom(seed=0)


def _two_views(room, eye_b=(2.4, 1.2, 0.9)):
    """Camera A and B look at the same wall corner; the room's box hides part of what A sees from B."""
    K = toy_intrinsics(W, H)
    A = look_at([1.0, 2.2, 1.0], [5.9, 3.6, 0.8])
    B = look_at(list(eye_b), [5.9, 3.6, 0.8])
    (ca, da), (cb, db) = render(room, A, K, W, H), render(room, B, K, W, H)
    return K, A, B, da, db


def _ground_truth(room, K, A, B, da):
    """Per valid source pixel: in B's image, truly visible from B (ray cast from B hits the same point)."""
    pts, vu = backproject(da, K)
    P = transform_points(A, pts)
    Pb = transform_points(invert(B), P)
    uv, z = project(Pb, K)
    ui, vi = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = (z > 0) & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    dirs = (Pb / z[:, None]) @ B[:3, :3].T  # camera z = 1: the ray parameter is the depth
    t, _ = room.raycast(np.broadcast_to(B[:3, 3], dirs.shape).copy(), dirs)
    return vu, P, inside, inside & (np.abs(t - z) < 1e-6)


def test_correspondences_reproject_exactly_and_reject_occluded_pixels(room):
    K, A, B, da, db = _two_views(room)
    m = pixel_correspondences(da, K, db, K, relative_pose(A, B), depth_tolerance=0.05, depth_tolerance_rel=0.02)
    vu, P, inside, visible = _ground_truth(room, K, A, B, da)
    assert m.n_valid == len(vu) == H * W and m.n_in_view == int(inside.sum())
    occluded = inside & ~visible
    assert occluded.sum() > 300  # the box hides part of the far walls from B

    # reprojection: the ray of B through tgt_uv hits the very point A saw (no pose-convention slip)
    rays = np.stack([(m.tgt_uv[:, 0] - K[0, 2]) / K[0, 0], (m.tgt_uv[:, 1] - K[1, 2]) / K[1, 1],
                     np.ones(len(m))], 1) @ B[:3, :3].T
    t, _ = room.raycast(np.broadcast_to(B[:3, 3], rays.shape).copy(), rays)
    hit = B[:3, 3] + t[:, None] * rays
    lin = m.src_pix[:, 0] * W + m.src_pix[:, 1]
    err = np.linalg.norm(hit - P[lin], axis=1)
    vis_lin = visible[lin]
    assert np.median(err) < 1e-5 and np.mean(err[vis_lin] < 1e-4) == 1.0  # float32 depth maps
    # the nearest target pixel is the rounded projection
    np.testing.assert_array_equal(m.tgt_pix, np.rint(m.tgt_uv[:, ::-1]).astype(np.int64))

    # visibility check agrees with ray casting except on a few occlusion-edge pixels
    accepted = np.zeros(H * W, bool)
    accepted[lin] = True
    agree = np.mean(accepted[inside] == visible[inside])
    assert agree > 0.99, agree
    assert (accepted & occluded).sum() <= 5 and (accepted & ~inside).sum() == 0
    # without the check the occluded pixels would have been taken
    loose = pixel_correspondences(da, K, db, K, relative_pose(A, B), depth_tolerance=100.0)
    assert len(loose) == m.n_in_view and len(loose) - len(m) > 300


def test_identity_pose_matches_every_pixel_to_itself_and_holes_are_rejected(room):
    K, A, _, da, _ = _two_views(room)
    m = pixel_correspondences(da, K, da, K, np.eye(4))
    assert len(m) == H * W and m.overlap == 1.0
    np.testing.assert_allclose(m.tgt_uv, m.src_pix[:, ::-1].astype(float), atol=1e-9)
    holes = da.copy()
    holes[10:20, 30:50] = 0.0  # the target sensor saw nothing there
    m2 = pixel_correspondences(da, K, holes, K, np.eye(4))
    assert len(m2) == H * W - 200
    assert not np.any((m2.tgt_pix[:, 0] >= 10) & (m2.tgt_pix[:, 0] < 20) & (m2.tgt_pix[:, 1] >= 30)
                      & (m2.tgt_pix[:, 1] < 50))
    # depth disagreeing by more than the tolerance: rejected
    far = da + 0.5
    assert len(pixel_correspondences(da, K, far, K, np.eye(4), depth_tolerance=0.05, depth_tolerance_rel=0.02)) == 0


def test_view_pairs_follow_frame_gap_and_overlap(room):
    K = toy_intrinsics(W, H)
    poses = pan_path(np.array([1.2, 1.0, 1.5]), 0.0, 90.0, 10)  # 10 degrees per frame
    depths = [render(room, P, K, W, H)[1] for P in poses]
    allp = select_view_pairs(depths, np.stack(poses), K, 1, 9, 0.0, 1.0, stride=4)
    assert len(allp) == 45
    ov = {(a, b): o for a, b, o in allp}
    assert ov[(0, 1)] > ov[(0, 3)] > ov[(0, 6)]  # overlap falls as the camera turns away
    sel = select_view_pairs(depths, np.stack(poses), K, 2, 4, 0.4, 0.8, stride=4)
    assert sel and all(2 <= b - a <= 4 and 0.4 <= o <= 0.8 for a, b, o in sel)
    assert {(a, b) for a, b, _ in sel} == {(a, b) for (a, b), o in ov.items() if 2 <= b - a <= 4 and 0.4 <= o <= 0.8}
    # the overlap is the two-way minimum
    a, b = 0, 3
    T = relative_pose(poses[a], poses[b])
    two_way = min(overlap_ratio(depths[a], K, depths[b], K, T, stride=4),
                  overlap_ratio(depths[b], K, depths[a], K, invert(T), stride=4))
    assert ov[(a, b)] == pytest.approx(two_way)


def test_sampling_and_resizing(room):
    K, A, B, da, db = _two_views(room)
    m = pixel_correspondences(da, K, db, K, relative_pose(A, B))
    rng = np.random.default_rng(0)
    s = sample_matches(m, 100, rng)
    assert len(s) == 100 and len({tuple(p) for p in s.src_pix}) == 100
    assert len(sample_matches(m, 10**6, rng)) == len(m)
    for _ in range(5):  # crops share correspondences, given in crop coordinates
        (va, ua), (vb, ub), cm = crop_pair(m, da.shape, db.shape, (32, 40), rng)
        assert len(cm) > 0 and 0 <= va <= H - 32 and 0 <= ub <= W - 40
        assert cm.src_pix.min() >= 0 and cm.src_pix[:, 0].max() < 32 and cm.tgt_pix[:, 1].max() < 40
        full = {(tuple(a), tuple(b)) for a, b in zip(m.src_pix, m.tgt_pix)}
        assert all((tuple(a + [va, ua]), tuple(b + [vb, ub])) in full for a, b in zip(cm.src_pix, cm.tgt_pix))
        np.testing.assert_array_equal(np.rint(cm.tgt_uv[:, ::-1]).astype(np.int64), cm.tgt_pix)
    color = render(room, A, K, W, H)[0]
    c2, d2, K2 = resize_view(color, da, K, (30, 40))
    assert c2.shape == (30, 40, 3) and d2.shape == (30, 40)
    assert set(np.unique(d2)) <= set(np.unique(da))  # nearest neighbour: no mixed depths
    # 1/5 size: the new pixel centres fall on old ones, so depth and scaled intrinsics agree exactly
    c5, d5, K5 = resize_view(color, da, K, (12, 16))
    pts, vu = backproject(d5, K5)
    uv, z = project(pts, K)
    ui, vi = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    assert np.median(np.abs(da[vi, ui] - z)) < 1e-6


# --------------------------------------------------------------------------- loss and metric


def test_info_nce_on_hand_made_features():
    n, T = 8, 0.4
    eye = torch.eye(n)
    perfect = float(info_nce(eye, eye, temperature=T))
    assert perfect == pytest.approx(math.log(1 + (n - 1) * math.exp(-1 / T)), rel=1e-6)
    assert float(info_nce(3.0 * eye, eye, temperature=T, symmetric=False)) == pytest.approx(perfect, rel=1e-6)
    const = torch.ones(n, 4)
    assert float(info_nce(const, const, temperature=T)) == pytest.approx(math.log(n), rel=1e-6)
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(512, 64, generator=g), torch.randn(512, 64, generator=g)
    assert abs(float(info_nce(a, b)) - math.log(512)) < 0.15  # unrelated features: chance
    # shuffled correspondences of perfect features: each row's target logit is 0, a wrong one is 1/T
    perm = torch.roll(torch.arange(n), 1)
    assert float(info_nce(eye, eye[perm], temperature=T)) == pytest.approx(math.log(math.exp(1 / T) + n - 1), rel=1e-6)
    # gradients pull corresponding features together
    x = torch.randn(16, 8, generator=g, requires_grad=True)
    y = torch.randn(16, 8, generator=g)
    loss0 = info_nce(x, y)
    loss0.backward()
    with torch.no_grad():
        x2 = x - 1.0 * x.grad
    assert float(info_nce(x2, y)) < float(loss0.detach())
    with pytest.raises(ValueError):
        info_nce(torch.ones(4, 3), torch.ones(5, 3))


def test_match_accuracy_on_identical_shifted_and_shuffled_features():
    g = torch.Generator().manual_seed(0)
    feat = torch.randn(16, H, W, generator=g)
    valid = np.ones((H, W), bool)
    rng = np.random.default_rng(0)
    pix = np.stack([rng.integers(0, H, 200), rng.integers(0, W, 200)], 1)
    uv = pix[:, ::-1].astype(float)
    acc, hits = match_accuracy(feat, feat, pix, uv, valid, threshold=0.5)
    assert acc == 1.0 and hits.all()
    # target = source shifted by (du, dv) = (5, 3): the true positions move with it
    shifted = torch.roll(feat, shifts=(3, 5), dims=(1, 2))
    acc, _ = match_accuracy(feat, shifted, pix, uv + [5, 3], valid, threshold=0.5)
    assert acc > 0.85  # pixels wrapping around the border land elsewhere
    # wrong truth by 2 px: a miss at threshold 1, a hit at 3
    assert match_accuracy(feat, feat, pix, uv + [2, 0], valid, threshold=1.0)[0] == 0.0
    assert match_accuracy(feat, feat, pix, uv + [2, 0], valid, threshold=3.0)[0] == 1.0
    # shuffled target pixels: chance (a 3 px disc is ~28 of 4800 pixels)
    perm = torch.randperm(H * W, generator=g)
    shuffled = feat.reshape(16, -1)[:, perm].reshape(16, H, W)
    assert match_accuracy(feat, shuffled, pix, uv, valid, threshold=3.0)[0] < 0.05
    # only valid target pixels are candidates
    no_self = valid.copy()
    no_self[pix[0, 0], pix[0, 1]] = False
    _, hits = match_accuracy(feat, feat, pix[:1], uv[:1], no_self, threshold=0.5)
    assert not hits[0]
    np.testing.assert_array_equal(gather_pixels(feat, pix[:3]).numpy(), feat[:, pix[:3, 0], pix[:3, 1]].T.numpy())


def test_color_jitter_changes_each_image_within_range():
    x = torch.rand(4, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    assert color_jitter(x, 0.0) is x
    y = color_jitter(x, 0.3, torch.Generator().manual_seed(1))
    assert y.shape == x.shape and float(y.min()) >= 0 and float(y.max()) <= 1
    ratios = [float((y[k] / x[k].clamp(min=1e-3)).median()) for k in range(4)]
    assert len({round(r, 3) for r in ratios}) == 4 and not torch.allclose(x, y)


# --------------------------------------------------------------------------- a small data set


def write_rgbd_layout(root: Path, scenes=("toy-a", "toy-b", "toy-c"), frames: int = 8, width: int = W,
                      height: int = H) -> Path:
    """Ray-cast RGB-D sequences of toy rooms in the 3DMatch layout (no fragments: not needed here)."""
    layout = Layout(root)
    K = toy_intrinsics(width, height)
    for k, scene in enumerate(scenes):
        room = ToyRoom(seed=k)
        poses = pan_path(np.array([1.2, 1.0, 1.5]) + 0.1 * k, 0.0 + 10 * k, 70.0 + 10 * k, frames,
                         step=[0.03, 0.02, 0.0])
        seq_dir = layout.rgbd_dir(scene) / "seq-01"
        seq_dir.mkdir(parents=True, exist_ok=True)
        write_matrix(layout.intrinsics(scene), K)
        for fid, P in enumerate(poses):
            color, depth = render(room, P, K, width, height)
            c, d, p = frame_paths(layout.frame_prefix(scene, "seq-01", fid))
            write_color(c, color)
            write_depth(d, depth)
            write_matrix(p, P)
    write_split(layout.split_file("train"), scenes[:-1])
    write_split(layout.split_file("val"), scenes[-1:])
    write_split(layout.split_file("test"), [])
    return root


@pytest.fixture(scope="module")
def rgbd_root(tmp_path_factory) -> Path:
    return write_rgbd_layout(tmp_path_factory.mktemp("rgbd") / "toy")


def test_frames_are_cached_reread_identically_and_bad_poses_skipped(tmp_path):
    from pcrcg.pretrain2d.frames import FrameCache, list_sequences, load_sequence

    root = write_rgbd_layout(tmp_path / "d", scenes=("s0", "s1"), frames=4, width=40, height=30)
    layout = Layout(root)
    (layout.frame_prefix("s0", "seq-01", 2).parent / "frame-000002.pose.txt").write_text("nan " * 16)
    assert list_sequences(layout, "s0") == [("seq-01", [0, 1, 2, 3])]
    cache = FrameCache(2)
    sq = load_sequence(layout, "s0", "seq-01", [0, 1, 2, 3], (24, 32), 4, cache)
    assert sq.frame_ids == [0, 1, 3] and sq.skipped == 1 and len(cache) == 2 and cache.misses == 0
    c3, d3 = sq.frame(2)  # frame id 3 was not cached: read again from disk
    assert cache.misses == 1 and c3.shape == (24, 32, 3) and d3.shape == (24, 32)
    c0, d0 = sq.frame(0)  # evicted by now: read again, identical
    fresh = load_sequence(layout, "s0", "seq-01", [0], (24, 32), 4, FrameCache(5))
    np.testing.assert_array_equal(c0, fresh.frame(0)[0])
    np.testing.assert_array_equal(d0, fresh.frame(0)[1])
    assert sq.coarse_depths.shape == (3, 6, 8)
    with pytest.raises(DataError, match="rgbd"):
        list_sequences(layout, "nosuchscene")


def small_cfg(root: Path, out: Path, *extra: str):
    from conftest import compose

    return compose("pretrain2d", ["profile=tiny", "logger=none", "prepare=false", f"data.root={root}",
                                  f"out={out}", "image_size=[48,64]", "train.crop=[32,48]", "encoder2d.out_dim=8",
                                  "encoder2d.decoder_channels=[32,16,16,8,8]", "train.steps=3",
                                  "train.batch_pairs=2", "train.points=128", "eval.pairs=3", "eval.points=50",
                                  "runtime.progress=false", *extra])


def test_a_few_steps_lower_the_loss_on_fixed_pairs(rgbd_root, tmp_path):
    from omegaconf import OmegaConf

    from pcrcg.pretrain2d.core import check_settings, load_split_sequences, make_optimizer, scene_pairs, train_step
    from pcrcg.vision.encoders import build_encoder

    torch.set_num_threads(1)
    data = OmegaConf.to_container(small_cfg(rgbd_root, tmp_path / "x.pth"), resolve=True)
    s = check_settings(data)
    seqs = load_split_sequences(Layout(rgbd_root), ["train"], s, lambda m: None, "train.splits")
    assert [len(q) for q in seqs] == [8, 8] and seqs[0].frame(3)[0].shape == (48, 64, 3)
    assert seqs[0].coarse_depths.shape == (8, 6, 8)  # 48x64 / overlap_stride 8
    pairs = scene_pairs(seqs, s, np.random.default_rng(0), None)
    assert pairs and all(s.min_overlap <= p.overlap <= s.max_overlap for p in pairs)
    torch.manual_seed(0)
    model = build_encoder(data["encoder2d"])
    opt = make_optimizer(model, s)
    batch = pairs[:2]
    losses = []
    for _ in range(8):  # the same pairs and pixels every step
        losses.append(train_step(model, opt, seqs, batch, s, np.random.default_rng(1), torch.Generator().manual_seed(2),
                                 torch.device("cpu")))
    assert losses[0] > 0.8 * math.log(s.points) and losses[-1] < 0.9 * losses[0], losses
    assert sum(b < a for a, b in zip(losses, losses[1:])) >= 5, losses


def test_pretrain_writes_a_checkpoint_that_runs_load(rgbd_root, tmp_path):
    from omegaconf import OmegaConf

    from conftest import compose
    from pcrcg.config import preflight
    from pcrcg.models.train import lifting_section
    from pcrcg.pretrain2d import pretrain
    from pcrcg.vision.encoders import build_encoder

    torch.set_num_threads(1)
    out = tmp_path / "ck" / "pri3d_resnet18.pth"
    cfg = small_cfg(rgbd_root, out)
    res = pretrain(cfg, base_dir=tmp_path, log=lambda m: None)
    for key in ("checkpoint", "loss_start", "loss_end", "match_acc_scratch", "match_acc_pretrained", "steps",
                "seconds", "pairs"):
        assert key in res, key
    assert res["checkpoint"] == str(out) and out.is_file() and res["steps"] == 3 and res["pairs"] > 0
    assert 0 <= res["match_acc_scratch"] <= 1 and 0 <= res["match_acc_pretrained"] <= 1
    assert res["eval_pairs"] == 3 and res["eval_points"] == 150 and res["eval_split"] == "val"
    json.dumps(res)

    # build_encoder loads it (and refuses another width)
    enc = {"name": "pri3d", "arch": "resnet18", "weights": str(out), "out_dim": 8,
           "decoder_channels": [32, 16, 16, 8, 8]}
    model = build_encoder(enc)
    saved = torch.load(out, map_location="cpu", weights_only=True)
    assert saved["meta"]["config_hash"] == res["config_hash"]
    torch.testing.assert_close(model.state_dict()["decoder.head.weight"], saved["state_dict"]["decoder.head.weight"])
    with pytest.raises(DataError, match="encoder2d.weights"):
        build_encoder({**enc, "out_dim": 16})

    # through a composed run config: encoder2d=pri3d encoder2d.weights=PATH, deep features lifted
    run_cfg = compose("run", ["profile=tiny", "encoder2d=pri3d", f"encoder2d.weights={out}", "encoder2d.out_dim=8",
                              "encoder2d.decoder_channels=[32,16,16,8,8]", "features=deep", "projection=implicit",
                              "logger=none"])
    preflight(run_cfg)
    lifting = lifting_section(OmegaConf.to_container(run_cfg, resolve=True))
    from pcrcg.models.module import PCRCGModule

    module = PCRCGModule(OmegaConf.to_container(run_cfg.model, resolve=True), lifting=lifting)
    loaded = {k: v for k, v in module.state_dict().items() if k.endswith("decoder.head.weight")}
    assert len(loaded) == 1
    torch.testing.assert_close(next(iter(loaded.values())), saved["state_dict"]["decoder.head.weight"])

    # the same config again: reused, not retrained
    again = pretrain(cfg, base_dir=tmp_path, log=lambda m: None)
    assert again["reused"] is True and again["match_acc_pretrained"] == res["match_acc_pretrained"]


def test_held_out_frames_when_the_eval_split_is_empty(rgbd_root, tmp_path):
    from pcrcg.pretrain2d import pretrain

    torch.set_num_threads(1)
    msgs = []
    res = pretrain(small_cfg(rgbd_root, tmp_path / "h.pth", "eval.split=test", "train.steps=1"), base_dir=tmp_path,
                   log=msgs.append)
    assert res["eval_split"] == "holdout" and any("held-out frames" in m for m in msgs)


@pytest.mark.parametrize("override, setting", [
    ("pairs.min_overlap=1.5", "pairs.min_overlap"),
    ("pairs.max_frame_gap=0", "pairs.max_frame_gap"),
    ("train.temperature=0", "train.temperature"),
    ("train.optimizer=lbfgs", "train.optimizer"),
    ("image_size=[10,10]", "image_size"),
    ("train.crop=[200,80]", "train.crop"),
    ("eval.pixel_threshold=-1", "eval.pixel_threshold"),
    ("encoder2d.arch=resnet7", "encoder2d.arch"),
    ("train.splits=[nosuchsplit]", "train.splits"),
])
def test_bad_settings_are_named_before_work(rgbd_root, tmp_path, override, setting):
    from pcrcg.pretrain2d import pretrain

    with pytest.raises((ConfigError, DataError), match=setting.replace(".", r"\.")):
        pretrain(small_cfg(rgbd_root, tmp_path / "b.pth", override), base_dir=tmp_path, log=lambda m: None)
    assert not (tmp_path / "b.pth").exists()


def test_missing_data_root_is_named(tmp_path):
    from pcrcg.pretrain2d import pretrain

    with pytest.raises(DataError, match="data.root"):
        pretrain(small_cfg(tmp_path / "nowhere", tmp_path / "m.pth"), base_dir=tmp_path, log=lambda m: None)


@pytest.mark.slow
def test_cli_prints_the_result_as_its_last_line_and_logs_to_mlflow(rgbd_root, tmp_path):
    import os

    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}", "OMP_NUM_THREADS": "1"}
    out = tmp_path / "cli.pth"
    cmd = [sys.executable, "-m", "pcrcg.pretrain2d", "profile=tiny", "prepare=false", f"data.root={rgbd_root}",
           f"out={out}", "image_size=[48,64]", "train.crop=null", "train.steps=2", "train.batch_pairs=1",
           "train.points=64", "eval.pairs=2", "eval.points=20", f"hydra.run.dir={tmp_path / 'hydra'}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["checkpoint"] == str(out) and out.is_file() and res["run_id"]
    from mlflow.tracking import MlflowClient

    run = MlflowClient(env["MLFLOW_TRACKING_URI"]).get_run(res["run_id"])
    assert run.info.status == "FINISHED" and run.data.tags["checkpoint"] == str(out)
    from pcrcg.tracking.git import code_version

    assert run.data.tags["code_version"] == code_version() and run.data.tags["profile"] == "tiny"
    assert "match_acc_pretrained" in run.data.metrics and run.data.params["train.steps"] == "2"
    hist = MlflowClient(env["MLFLOW_TRACKING_URI"]).get_metric_history(res["run_id"], "train/loss")
    assert len(hist) == 2
    bad = subprocess.run(cmd[:3] + ["prepare=false", f"data.root={tmp_path / 'nowhere'}", "logger=none",
                                    f"hydra.run.dir={tmp_path / 'hydra2'}"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "data.root" in bad.stderr and bad.stdout.strip() == ""
