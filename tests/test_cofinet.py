"""CoFiNet (model=cofinet): each block on small inputs with known answers, then the backbone trained
and evaluated through ``python -m pcrcg.run model=cofinet profile=tiny`` with and without color (issue 15)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from conftest import REPO, compose
from pcrcg.errors import ConfigError
from pcrcg.geometry import make_transform, random_rotation
from pcrcg.models.cofinet import CoFiNetConfig, build_cofinet
from pcrcg.models.cofinet.attention import masked_instance_norm
from pcrcg.models.cofinet.loss import matching_loss
from pcrcg.models.cofinet.matching import (
    coarse_targets,
    fine_correspondences,
    fine_targets,
    nearest_node,
    select_node_pairs,
)
from pcrcg.models.geotransformer.superpoints import point_to_node_partition


def _model_cfg(*overrides: str) -> dict:
    cfg = compose("run", ["model=cofinet", "profile=tiny", *overrides])
    return OmegaConf.to_container(cfg.model, resolve=True)


def _net(**kw) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_cofinet({**_model_cfg(), **kw})


def rigid(seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(make_transform(random_rotation(rng, math.pi), rng.normal(0, 1.0, 3)))


def move(T: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    T = T.to(p.dtype)
    return p @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- the matching layers


def test_coarse_matching_layer_marginals():
    """Coarse: every node's row and column sum to 1 (dustbin included), the dustbin row to Mt and the
    dustbin column to Ms (SuperGlue's marginals); the learned dustbin score is a parameter."""
    net = _net().double()
    g = torch.Generator().manual_seed(1)
    src, tgt = torch.randn(7, 32, generator=g, dtype=torch.float64), torch.randn(5, 32, generator=g, dtype=torch.float64)
    with torch.no_grad():
        P = torch.exp(net.coarse_matching(src, tgt))
    assert P.shape == (8, 6)
    torch.testing.assert_close(P[:7].sum(1), torch.ones(7, dtype=torch.float64), atol=1e-4, rtol=0)
    torch.testing.assert_close(P[:, :5].sum(0), torch.ones(5, dtype=torch.float64), atol=1e-4, rtol=0)
    assert abs(float(P[7].sum()) - 5) < 1e-3 and abs(float(P[:, 5].sum()) - 7) < 1e-3
    assert "coarse_transport.alpha" in dict(net.named_parameters())


def test_fine_matching_layer_marginals_with_padding():
    """Fine: patches of different sizes in one batch; real rows and columns sum to 1, padding carries
    no mass, the dustbin row holds one unit per real target point; gradients stay finite."""
    net = _net().double()
    g = torch.Generator().manual_seed(2)
    fs = torch.randn(3, 6, 16, generator=g, dtype=torch.float64, requires_grad=True)
    ft = torch.randn(3, 6, 16, generator=g, dtype=torch.float64)
    sm = torch.tensor([[1] * 6, [1] * 4 + [0] * 2, [1] * 1 + [0] * 5], dtype=torch.bool)
    tm = torch.tensor([[1] * 3 + [0] * 3, [1] * 6, [1] * 2 + [0] * 4], dtype=torch.bool)
    la = net.fine_matching(fs, ft, sm, tm)
    P = torch.exp(la)
    assert P.shape == (3, 7, 7)
    for b in range(3):
        m, n = int(sm[b].sum()), int(tm[b].sum())
        torch.testing.assert_close(P[b, :m].sum(1), torch.ones(m, dtype=torch.float64), atol=1e-4, rtol=0)
        torch.testing.assert_close(P[b, :, :n].sum(0), torch.ones(n, dtype=torch.float64), atol=1e-4, rtol=0)
        assert float(P[b, m:6].sum()) < 1e-12 and float(P[b, :, n:6].sum()) < 1e-12  # padding
        assert abs(float(P[b, 6, :n].sum()) + float(P[b, 6, 6]) - n) < 1e-3  # dustbin row (with the corner)
    la[:, :6, :6].masked_fill(~(sm.unsqueeze(2) & tm.unsqueeze(1)), 0).sum().backward()
    assert bool(torch.isfinite(fs.grad).all()) and float(fs.grad.abs().sum()) > 0


def test_masked_instance_norm_ignores_padding():
    x = torch.randn(2, 5, 3, dtype=torch.float64)
    mask = torch.tensor([[1, 1, 1, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    y = masked_instance_norm(x, mask)
    ref = torch.nn.functional.instance_norm(x[0:1, :3].transpose(1, 2)).transpose(1, 2)
    torch.testing.assert_close(y[0:1, :3], ref)
    x2 = x.clone()
    x2[0, 3:] = 1e6  # padding values change nothing on the real points
    torch.testing.assert_close(masked_instance_norm(x2, mask)[0, :3], y[0, :3])


# --------------------------------------------------------------------------- patches and coarse ground truth


def _toy_pyramid(voxel: float = 0.1, layers: int = 3):
    from pcrcg.models.datamodule import PairCollate
    from pcrcg.models.kpconv import PyramidSpec, calibrate_limits
    from pcrcg.testing.pairs import toy_pair

    s = toy_pair(0, density=80.0)
    spec = PyramidSpec(voxel, layers, 2.5)
    spec = PyramidSpec(voxel, layers, 2.5, calibrate_limits([s.src_points, s.tgt_points], spec))
    return PairCollate(spec, overlap_radius=1.5 * voxel)([s])


def test_node_patches_hold_each_point_in_its_nearest_nodes_patch_within_the_radius():
    batch = _toy_pyramid()
    ns, _ = batch.pyramid.split(0)
    msc, _ = batch.pyramid.split(2)
    pts, nodes = batch.pyramid.points[0][:ns], batch.pyramid.points[2][:msc]
    owner = torch.cdist(pts, nodes).argmin(1)
    # room for every point: each point is in exactly its nearest node's patch
    whole = point_to_node_partition(pts, nodes, len(pts))
    where = torch.full((len(pts),), -1)
    rows = torch.arange(len(nodes)).unsqueeze(1).expand_as(whole.indices)
    where[whole.indices[whole.mask]] = rows[whole.mask]
    assert int(whole.mask.sum()) == len(pts)
    assert torch.equal(where, owner) and torch.equal(nearest_node(pts, nodes), owner)
    cell = 0.1 * 2**2  # the nodes' grid
    d = torch.linalg.vector_norm(pts - nodes[owner], dim=1)
    assert float(d.max()) <= math.sqrt(3) * cell  # a point and its node share a grid cell
    # K = 16 (4^(L-1)): a patch holds its node's 16 nearest points (all of them when it owns fewer)
    p = point_to_node_partition(pts, nodes, 16)
    counts = torch.bincount(owner, minlength=len(nodes))
    assert torch.equal(p.mask.sum(1), counts.clamp(max=16)) and torch.equal(p.node_mask, counts > 0)
    for m in range(len(nodes)):
        inside = p.indices[m][p.mask[m]]
        assert bool((owner[inside] == m).all())
        left = torch.tensor(sorted(set((owner == m).nonzero().squeeze(1).tolist()) - set(inside.tolist())))
        if len(left):
            assert float(torch.linalg.vector_norm(pts[inside] - nodes[m], dim=1).max()) <= \
                float(torch.linalg.vector_norm(pts[left] - nodes[m], dim=1).min()) + 1e-6


def test_coarse_targets_on_a_hand_made_pair():
    """Two source nodes (4 points each), two target nodes (2 points each); three true point pairs:
    node 0 -> node 0 twice, node 0 -> node 1 once; source node 1 is not seen by the target."""
    sn = torch.tensor([[0.0, 0, 0], [10, 0, 0]])
    tn = torch.tensor([[0.0, 5, 0], [10, 5, 0]])
    sp = torch.cat([sn[0] + 0.1 * torch.randn(4, 3), sn[1] + 0.1 * torch.randn(4, 3)])
    tp = torch.cat([tn[0] + 0.1 * torch.randn(2, 3), tn[1] + 0.1 * torch.randn(2, 3)])
    corr = torch.tensor([[0, 0], [1, 1], [2, 2]])  # source 0, 1 -> target node 0; source 2 -> target node 1
    M = coarse_targets(sn, tn, sp, tp, corr)
    # visible ratios: source node 0 3/4, node 1 0; target node 0 2/2, node 1 1/2
    # (0, 0): min(2/3 * 3/4, 2/2 * 1) = 0.5; (0, 1): min(1/3 * 3/4, 1/1 * 1/2) = 0.25
    want = torch.tensor([[0.5, 0.25, 0.25], [0.0, 0.0, 1.0], [0.0, 0.5, 0.0]])
    torch.testing.assert_close(M, want)
    pairs, probs = select_node_pairs(torch.log(M.clamp(min=1e-12)), torch.ones(2, dtype=torch.bool),
                                     torch.ones(2, dtype=torch.bool), 0.2, 1)
    assert pairs.tolist() == [[0, 0], [0, 1]] and probs.tolist() == [0.5, 0.25]  # above the threshold
    pairs, _ = select_node_pairs(torch.log(M.clamp(min=1e-12)), torch.ones(2, dtype=torch.bool),
                                 torch.ones(2, dtype=torch.bool), 0.6, 1)
    assert pairs.tolist() == [[0, 0]]  # none above: the most probable
    assert float(matching_loss(torch.log(M.clamp(min=1e-12)), M)) > 0


# --------------------------------------------------------------------------- fine matching, known transform


def test_fine_matching_recovers_a_known_transform():
    """A synthetic pair: 40 node patches of 8 points, the target patches the source ones moved by T
    (shuffled, plus noise and one outlier per patch); fine features equal for true pairs. Sinkhorn in
    the patches, the correspondences and the project's RANSAC on them give T back; the fine labels
    are the true pairs."""
    from pcrcg.registration.correspondences import register_correspondences
    from pcrcg.registration.feature_registration import RegistrationConfig

    g = torch.Generator().manual_seed(3)
    T = rigid(4)
    P, K = 40, 8
    centres = torch.rand(P, 1, 3, generator=g, dtype=torch.float64) * 4
    src = centres + 0.3 * torch.randn(P, K, 3, generator=g, dtype=torch.float64)
    perm = torch.stack([torch.randperm(K, generator=g) for _ in range(P)])
    tgt = move(T, torch.gather(src, 1, perm.unsqueeze(2).expand(P, K, 3)))
    tgt = tgt + 0.002 * torch.randn(P, K, 3, generator=g, dtype=torch.float64)
    tgt[:, -1] += 3.0  # an outlier per target patch: its source partner has no match
    feats = torch.nn.functional.normalize(torch.randn(P, K, 16, generator=g, dtype=torch.float64), dim=2) * 6
    fs, ft = feats, torch.gather(feats, 1, perm.unsqueeze(2).expand(P, K, 16))
    mask = torch.ones(P, K, dtype=torch.bool)
    net = _net(local_attention=False).double()
    with torch.no_grad():
        net.fine_proj.weight.copy_(torch.eye(16))
        net.fine_proj.bias.zero_()
        la = net.fine_matching(fs, ft, mask, mask)
    labels = fine_targets(src, tgt, mask, mask, T, 0.02)
    truth = torch.zeros(P, K, K, dtype=torch.bool)
    truth[torch.arange(P).unsqueeze(1), perm, torch.arange(K)] = True
    truth[:, :, -1] = False
    assert torch.equal(labels[:, :K, :K] > 0, truth)
    assert torch.equal(labels[:, :K, K] > 0, ~truth.any(2)) and torch.equal(labels[:, K, :K] > 0, ~truth.any(1))
    gi, i, j, conf = fine_correspondences(la, mask, mask, torch.ones(P, dtype=torch.float64))
    right = truth[gi, i, j]
    assert float(right.float().mean()) > 0.8 and int(right.sum()) >= P * (K - 1) * 0.9
    pairs = torch.cat([src[gi, i], tgt[gi, j]], 1).numpy()
    cfg = RegistrationConfig(ransac={"distance": 0.05, "max_iterations": 5000})
    reg = register_correspondences(pairs, conf.numpy(), 250, cfg, seed=0)
    E = np.linalg.inv(T.numpy()) @ reg.transform
    assert len(reg.used) == min(250, len(pairs))
    assert math.degrees(math.acos(min(1.0, (np.trace(E[:3, :3]) - 1) / 2))) < 1.0 and np.linalg.norm(E[:3, 3]) < 0.02


def test_correspondences_are_drawn_by_confidence_without_replacement():
    from pcrcg.registration.correspondences import sample_correspondences

    scores = np.r_[np.full(10, 1.0), np.full(990, 1e-6)]
    idx = sample_correspondences(scores, 20, np.random.default_rng(0))
    assert len(set(idx.tolist())) == 20 and set(range(10)) <= set(idx.tolist())
    assert sample_correspondences(scores[:5], 20, np.random.default_rng(0)).tolist() == list(range(5))
    zeros = sample_correspondences(np.zeros(30), 10, np.random.default_rng(0))
    assert len(set(zeros.tolist())) == 10


def test_evaluation_registers_with_ransac_on_the_models_correspondences():
    """A pair whose outputs carry correspondences (300 true among 700 outliers, the true ones more
    confident) and useless descriptors: evaluated at N = 250 from the correspondences it registers
    (RR 100, a high inlier ratio); the same outputs without them go through the descriptors and fail."""
    from pcrcg.evaluation.metrics import PairRecord, SceneGT, information_matrix
    from pcrcg.evaluation.model import evaluate_model_outputs
    from pcrcg.models.module import PairOutput
    from pcrcg.registration.feature_registration import FragmentOutput, RegistrationConfig

    rng = np.random.default_rng(5)
    T = rigid(6).numpy()
    src_pts = rng.uniform(-1, 1, (1000, 3)).astype(np.float32)
    tgt_pts = (src_pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    frag = lambda p: FragmentOutput(p, rng.normal(size=(len(p), 8)).astype(np.float32),  # noqa: E731
                                    np.ones(len(p), np.float32), np.ones(len(p), np.float32))
    true = np.concatenate([src_pts[:300], tgt_pts[:300]], 1)
    wrong = np.concatenate([src_pts[300:], tgt_pts[rng.permutation(700)]], 1)
    corr = np.concatenate([true, wrong]).astype(np.float32)
    scores = np.r_[np.full(300, 0.9), np.full(700, 0.3)].astype(np.float32)
    gt = {"s": SceneGT("s", (PairRecord("s", 0, 5, T, n_fragments=10),), T[None],
                       information_matrix(src_pts.astype(np.float64))[None])}
    cfg = RegistrationConfig(n_points=(250,), ransac={"distance": 0.05, "max_iterations": 5000})
    with_corr = PairOutput("s", 0, 5, frag(src_pts), frag(tgt_pts), T, correspondences=corr,
                           correspondence_scores=scores)
    m = evaluate_model_outputs([with_corr], gt, cfg=cfg, progress=False)
    assert m["rr_250"] == 100.0 and m["ir_250"] > 45.0 and m["fmr_250"] == 100.0
    plain = PairOutput("s", 0, 5, frag(src_pts), frag(tgt_pts), T)
    m = evaluate_model_outputs([plain], gt, cfg=cfg, progress=False)
    assert m["rr_250"] == 0.0 and m["ir_250"] < 5.0


# --------------------------------------------------------------------------- config


def test_config_sizes_and_bad_values():
    common = OmegaConf.load(REPO / "conf" / "model" / "common" / "kpconv.yaml")
    tiny, pred = _model_cfg(), OmegaConf.to_container(compose("run", ["profile=tiny"]).model, resolve=True)
    for key in common:
        assert tiny[key] == pred[key], key
    c = CoFiNetConfig.from_mapping(tiny)
    assert (c.first_dim, c.gnn_dim, c.num_heads, c.final_dim, c.patch_points) == (16, 32, 2, 16, 16)
    paper = CoFiNetConfig.from_mapping(_model_cfg("profile=paper"))
    assert (paper.voxel_size, paper.num_layers, paper.first_dim, paper.gnn_dim, paper.num_heads, paper.final_dim,
            paper.patch_points, paper.num_targets, paper.min_coarse_correspondences) == \
        (0.025, 4, 128, 256, 4, 32, 64, 128, 200)  # CoFiNet's 3DMatch sizes
    assert abs(paper.metres(paper.positive_radius) - 0.1) < 1e-12
    assert abs(paper.metres(paper.loss.overlap_radius) - 0.0375) < 1e-12
    from pcrcg.config import validate_run_config

    validate_run_config(compose("run", ["model=cofinet", "profile=tiny"]))
    for override, key in (("model.num_heads=3", "model.num_heads"), ("model.blocks=[self,bogus]", "model.blocks"),
                          ("model.positive_radius=-1", "model.positive_radius"),
                          ("model.coarse_threshold=1.5", "model.coarse_threshold"),
                          ("model.local_attention=maybe", "model.local_attention")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            validate_run_config(compose("run", ["model=cofinet", "profile=tiny", override]))


def test_a_bad_model_value_is_one_line_before_data_preparation(tmp_path):
    root = tmp_path / "never-made"
    p = subprocess.run([sys.executable, "-m", "pcrcg.run", "model=cofinet", "profile=tiny", "model.num_heads=3",
                        f"data.root={root}", "logger=none"], cwd=tmp_path, capture_output=True, text=True,
                       timeout=300, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    assert p.returncode == 2, p.stderr[-2000:]
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "model.num_heads" in lines[0], p.stderr[-2000:]
    assert not root.exists()  # the data were never prepared


def test_network_shapes_and_color_changes_only_the_first_layer():
    batch = _toy_pyramid(0.12)
    cfg = {**_model_cfg(), "voxel_size": 0.12}
    torch.manual_seed(0)
    net, net_c = build_cofinet(cfg, in_dim=1), build_cofinet(cfg, in_dim=33)
    sd, sd_c = net.state_dict(), net_c.state_dict()
    assert sd.keys() == sd_c.keys()
    assert [k for k in sd if sd[k].shape != sd_c[k].shape] == ["encoder.0.conv.weights"]
    n0 = batch.pyramid.points[0].shape[0]
    out = net(torch.ones(n0, 1), batch.pyramid, batch.corr, targets=True)
    k = net.cfg.patch_points
    assert out.log_assign.shape == (net.cfg.num_targets, k + 1, k + 1)
    assert out.src_feats_f.shape == (batch.n_src, net.cfg.final_dim)
    assert out.coarse_log.shape == (len(out.src_nodes) + 1, len(out.tgt_nodes) + 1)
    assert bool((out.coarse_mask[out.node_pairs[:, 0], out.node_pairs[:, 1]] > 0).all())  # true node pairs
    net.eval()
    with torch.no_grad():
        out = net(torch.ones(n0, 1), batch.pyramid)
        s, t, conf = net.correspondences(out)
    assert len(out.node_pairs) >= min(net.cfg.min_coarse_correspondences, len(out.src_nodes) * len(out.tgt_nodes))
    assert s.shape == t.shape and s.shape[1] == 3 and bool((conf > 0).all()) and bool((conf <= 1 + 1e-6).all())


# --------------------------------------------------------------------------- tiny profile, end to end


@pytest.mark.parametrize("color", [
    pytest.param([], id="geometry"),
    pytest.param(["features=deep", "projection=explicit", "encoder2d=scratch"], id="pcr-cg", marks=pytest.mark.slow),
])
def test_tiny_run_trains_and_evaluates_cofinet(tiny_root, tmp_path, monkeypatch, color):
    """``python -m pcrcg.run model=cofinet profile=tiny``: 4 steps, then RANSAC on N of the model's own
    correspondences at every N, per benchmark, with est.log files; the checkpoint's outputs keep their
    correspondences through the pair .npz."""
    from pcrcg.config import CONF_DIR
    from test_run_support import read_status_files, run_cli

    ns = [1000, 250]
    args = ["--config-path", str(CONF_DIR), "model=cofinet", "profile=tiny", f"data.root={tiny_root}", "logger=none",
            "data.workers=1", "eval.max_pairs=2", f"eval.n_points=[{ns[0]},{ns[1]}]", "runtime.report_on_end=false",
            "trainer.progress_bar=false", f"hydra.run.dir={tmp_path}/out", *color]
    assert run_cli(args, tmp_path, monkeypatch) == 0
    (status,) = read_status_files(tmp_path / "out")
    assert status["status"] == "finished", status.get("error")
    m = status["metrics"]
    for b in ("3DMatch", "3DLoMatch"):
        for n in ns:
            for key in ("rr", "fmr", "ir", "seconds_per_pair"):
                assert f"{b}/{key}_{n}" in m, (b, key, n)
            assert list((tmp_path / "out" / "eval" / "learned" / b / str(n)).glob("*/est.log"))
    assert "3DLoMatch/rr_lgr" not in m  # no model-own estimate: CoFiNet is registered by RANSAC
    (ckpt,) = list((tmp_path / "checkpoints").glob("*/model.ckpt"))
    from pcrcg.data.dataset import PairDataset
    from pcrcg.models.train import infer_clouds, load_module, load_pair_output, save_pair_output

    module = load_module(ckpt, device="cpu")
    assert module.kind == "cofinet" and (module.lifter is None) == (not color)
    assert module.in_dim == (1 if not color else 1 + int(module.lifter.out_dim))
    if not color:
        s = PairDataset(tiny_root, "3DMatch", 0)[0]
        out = infer_clouds(module, s.src_points, s.tgt_points)
        assert out.correspondences.shape[1] == 6 and len(out.correspondences) == len(out.correspondence_scores)
        assert len(out.src.points) == len(out.src.descriptors) < len(s.src_points)  # level-0 points at 6 cm
        back = load_pair_output(save_pair_output(out, tmp_path / "pair.npz"))
        np.testing.assert_allclose(back.correspondences, out.correspondences)
        np.testing.assert_allclose(back.correspondence_scores, out.correspondence_scores)
        # mode=pair answers RANSAC on N of the model's correspondences (the descriptor path's transform beside it)
        from pcrcg.evaluate import run as evaluate_run

        frags = tiny_root / "fragments" / s.scene
        res = evaluate_run(compose("evaluate", ["profile=tiny", "mode=pair", "method=learned", f"checkpoint={ckpt}", "pair_points=50",
                                                f"source={frags / f'cloud_bin_{s.j}.ply'}",
                                                f"target={frags / f'cloud_bin_{s.i}.ply'}"]))
        assert res["registration"] == "correspondences" and res["model_correspondences"] > 0
        assert res["correspondences"] == min(50, res["model_correspondences"]) and len(res["transform_features"]) == 4


@pytest.mark.slow
def test_training_on_one_pair_learns_to_match_and_register_it():
    """40 Adam steps on one toy pair (0.1 m voxels): the coarse matching finds overlapping node pairs,
    the fine correspondences become inliers and RANSAC on them registers the pair (measured: coarse
    precision 0.02 -> 0.81, correspondences within 0.1 m 1% -> 8%, RTE 4.26 -> 0.17 m, RRE 95 -> 5 deg)."""
    from pcrcg.models.module import PCRCGModule
    from pcrcg.registration.correspondences import register_correspondences
    from pcrcg.registration.feature_registration import RegistrationConfig

    torch.manual_seed(0)
    v = 0.1
    batch = _toy_pyramid(v)
    module = PCRCGModule({**_model_cfg(), "voxel_size": v}, optim={"name": "adam", "lr": 1e-3})
    opt = module.configure_optimizers()["optimizer"]
    gt = batch.transform.double().numpy()

    def check():
        module.eval()
        with torch.no_grad():
            out, _ = module(batch)
            precision = float(module.compute_stats(batch, out)["coarse_precision"])
            s, t, conf = module.net.correspondences(out)
        pairs = torch.cat([s, t], 1).double().numpy()
        ir = float((np.linalg.norm(pairs[:, :3] @ gt[:3, :3].T + gt[:3, 3] - pairs[:, 3:], axis=1) < 0.1).mean())
        T = register_correspondences(pairs, conf.numpy(), 1000,
                                     RegistrationConfig(ransac={"distance": 2 * v, "max_iterations": 5000}), 0).transform
        rre = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(T[:3, :3].T @ gt[:3, :3]) - 1) / 2))))
        return precision, ir, rre, float(np.linalg.norm(T[:3, 3] - gt[:3, 3]))

    p0, ir0, _, rte0 = check()
    for _ in range(40):
        module.train()
        loss = module.compute_stats(batch, module(batch)[0])["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    p1, ir1, rre1, rte1 = check()
    assert p0 < 0.2 and ir0 < 0.02 and rte0 > 0.5  # untrained: no overlapping node pairs, no registration
    assert p1 > 0.7 and ir1 > 0.06 and rre1 < 10.0 and rte1 < 0.3
    po = module.eval().predict_pair(batch)  # what the evaluation reads: the same pairs, in the fragments' frames
    c, T = po.correspondences.astype(np.float64), po.transform
    assert abs(float((np.linalg.norm(c[:, :3] @ T[:3, :3].T + T[:3, 3] - c[:, 3:], axis=1) < 0.1).mean()) - ir1) < 1e-6
