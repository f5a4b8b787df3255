"""`python -m pcrcg.evaluate` modes, the pipeline's evaluation stage and evaluate_model_outputs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from omegaconf import OmegaConf

from pcrcg.data.layout import Layout, PairRecord, write_gt_log, write_matrix, write_ply
from pcrcg.errors import ConfigError, DataError
from pcrcg.evaluation import evaluate_model_outputs, information_matrix, load_benchmark, read_estimates
from pcrcg.evaluation.metrics import SceneGT, rotation_error_deg
from pcrcg.geometry import axis_angle_to_matrix, make_transform
from pcrcg.registration import RansacConfig, RegistrationConfig
from pcrcg.testing.layouts import write_layout
from pcrcg.testing.pairs import make_fragment_pair, simulate_outputs
from pcrcg.testing.rooms import box_room

REPO = Path(__file__).resolve().parents[1]


def _compose(overrides: list[str], profile: str = "tiny"):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(config_name="evaluate", overrides=[f"profile={profile}", *overrides])


def _run(overrides: list[str]) -> dict:
    from pcrcg.evaluate import run

    out = run(_compose(overrides))
    json.dumps(out)  # JSON-ready
    return out


@pytest.fixture(scope="module")
def layout(tmp_path_factory) -> Path:
    return write_layout(tmp_path_factory.mktemp("lay") / "data", seed=0)


def _gt_as_estimates(root: Path, out: Path, perturb=None) -> Path:
    for b in ("3DMatch", "3DLoMatch"):
        for s, g in load_benchmark(Layout(root).benchmark_dir(b)).items():
            recs = [PairRecord(s, p.i, p.j, p.transform if perturb is None else p.transform @ perturb, n_fragments=p.n_fragments)
                    for p in g.pairs]
            write_gt_log(out / b / s / "est.log", recs)
    return out


# --------------------------------------------------------------------------- mode=score


def test_score_mode_subprocess_prints_json_last(layout, tmp_path):
    est = _gt_as_estimates(layout, tmp_path / "est")
    bench = Layout(layout).benchmark_dir("3DMatch")
    proc = subprocess.run(
        [sys.executable, "-m", "pcrcg.evaluate", "mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DMatch'}",
         f"hydra.run.dir={tmp_path / 'hydra'}"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["rr"] == 100.0 and out["scenes"] == {"room": 100.0} and out["n_counted"] == 3
    # a bad input: exit status 2 and one line naming the file
    proc = subprocess.run(
        [sys.executable, "-m", "pcrcg.evaluate", "mode=score", f"benchmark_dir={tmp_path / 'missing'}",
         f"estimate_dir={est}", f"hydra.run.dir={tmp_path / 'hydra'}"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2 and f"{tmp_path / 'missing'}: benchmark folder does not exist" in proc.stderr


def test_score_mode_counts_failures_and_missing(layout, tmp_path):
    est = _gt_as_estimates(layout, tmp_path / "est", perturb=make_transform(np.eye(3), [0.5, 0, 0]))
    bench = Layout(layout).benchmark_dir("3DMatch")
    out = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DMatch'}"])
    assert out["rr"] == 0.0 and out["n_success"] == 0
    (est / "3DMatch" / "room" / "est.log").unlink()
    out = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DMatch'}"])
    assert out["rr"] == 0.0 and out["missing_scenes"] == ["room"] and out["n_missing"] == 7


def test_score_mode_bad_inputs_name_the_file(layout, tmp_path):
    bench = Layout(layout).benchmark_dir("3DMatch")
    with pytest.raises(ConfigError, match="estimate_dir"):
        _run(["mode=score", f"benchmark_dir={bench}"])
    with pytest.raises(DataError, match="does-not-exist"):
        _run(["mode=score", f"benchmark_dir={tmp_path / 'does-not-exist'}", f"estimate_dir={tmp_path}"])
    est = _gt_as_estimates(layout, tmp_path / "est")
    f = est / "3DMatch" / "room" / "est.log"
    f.write_text(f.read_text().replace("1.0000000000e+00", "1.0000000000e+00 7", 1))  # 5 numbers on a row
    with pytest.raises(DataError, match=str(f)):
        _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DMatch'}"])
    # a benchmark scene without gt.info
    import shutil

    b2 = tmp_path / "bench2"
    shutil.copytree(bench, b2)
    (b2 / "room" / "gt.info").unlink()
    with pytest.raises(DataError, match=r"gt\.info"):
        _run(["mode=score", f"benchmark_dir={b2}", f"estimate_dir={est / '3DMatch'}"])
    with pytest.raises(ConfigError, match="mode"):
        _run(["mode=nope"])


# --------------------------------------------------------------------------- mode=pair


@pytest.fixture(scope="module")
def clouds(tmp_path_factory):
    d = tmp_path_factory.mktemp("pair")
    rng = np.random.default_rng(4)
    pts, cols = box_room(rng, 30000)
    pair = make_fragment_pair(rng, pts, cols, crop=0.2, voxel=0.04)
    write_ply(d / "src.ply", pair.src_points, pair.src_colors)
    np.savez(d / "tgt.npz", points=pair.tgt_points, colors=pair.tgt_colors)
    write_ply(d / "tgt.ply", pair.tgt_points, pair.tgt_colors)
    init = pair.transform @ make_transform(axis_angle_to_matrix([0, 0, 1], np.radians(3)), [0.03, 0.0, -0.02])
    write_matrix(d / "init.txt", init)
    return d, pair


def test_pair_mode_icp_from_an_initial_estimate(clouds):
    d, pair = clouds
    out = _run(["mode=pair", "method=icp", f"source={d / 'src.ply'}", f"target={d / 'tgt.npz'}", f"init={d / 'init.txt'}"])
    T = np.array(out["transform"])
    assert T.shape == (4, 4)
    assert rotation_error_deg(T[:3, :3], pair.transform[:3, :3]) < 1.0
    assert np.linalg.norm(T[:3, 3] - pair.transform[:3, 3]) < 0.02


def test_pair_mode_color_icp_and_errors(clouds, tmp_path):
    d, pair = clouds
    out = _run(["mode=pair", "method=color_icp", f"source={d / 'src.ply'}", f"target={d / 'tgt.ply'}",
                f"init={d / 'init.txt'}"])
    assert np.linalg.norm(np.array(out["transform"])[:3, 3] - pair.transform[:3, 3]) < 0.02
    np.savez(tmp_path / "nocol.npz", points=pair.tgt_points)
    with pytest.raises(DataError, match="nocol.npz"):
        _run(["mode=pair", "method=color_icp", f"source={d / 'src.ply'}", f"target={tmp_path / 'nocol.npz'}"])
    with pytest.raises(DataError, match="missing.ply"):
        _run(["mode=pair", "method=icp", f"source={d / 'missing.ply'}", f"target={d / 'tgt.ply'}"])
    (tmp_path / "bad.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(DataError, match="bad.txt"):
        _run(["mode=pair", "method=icp", f"source={d / 'src.ply'}", f"target={d / 'tgt.ply'}", f"init={tmp_path / 'bad.txt'}"])
    with pytest.raises(ConfigError, match="method"):
        _run(["mode=pair", "method=magic", f"source={d / 'src.ply'}", f"target={d / 'tgt.ply'}"])


# --------------------------------------------------------------------------- mode=benchmark


def test_benchmark_mode_icp_from_given_estimates(layout, tmp_path):
    init = _gt_as_estimates(layout, tmp_path / "init",
                            perturb=make_transform(axis_angle_to_matrix([1, 0, 0], np.radians(2)), [0.02, 0, 0]))
    out = _run(["mode=benchmark", "method=icp", f"++data.root={layout}", f"out_dir={tmp_path / 'out'}",
                f"init_dir={init}"])
    assert out["benchmarks"]["3DMatch"]["rr"] == 100.0 and out["benchmarks"]["3DLoMatch"]["rr"] == 100.0
    assert out["benchmarks"]["3DMatch"]["rte"] < 0.02
    est = read_estimates(tmp_path / "out" / "3DMatch" / "room" / "est.log")
    assert len(est) == 7
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["benchmarks"]["3DMatch"]["protocol"]["pairs_counted_in_rr"] == 3
    with pytest.raises(DataError, match="nowhere"):
        _run(["mode=benchmark", "method=icp", f"++data.root={tmp_path / 'nowhere'}", f"out_dir={tmp_path / 'o2'}"])


def test_pipeline_evaluate_stage_with_a_classical_method(layout, tmp_path):
    from pcrcg.evaluation.stage import evaluate

    cfg = OmegaConf.create({"method": "fpfh", "seed": 0, "views": 2, "icp_init": "identity",
                            "eval": {"benchmarks": ["3DMatch"], "n_points": [1000], "ransac_iterations": 5000,
                                     "ransac_distance": 0.05, "inlier_distance": 0.1, "fmr_threshold": 0.05,
                                     "rmse_threshold": 0.2, "max_pairs": 3}})
    res = evaluate(cfg, data_root=layout, out_dir=tmp_path / "eval", progress=False)
    m = res["metrics"]
    assert {"3DMatch/rr", "3DMatch/rre", "3DMatch/rte", "3DMatch/fmr", "3DMatch/ir"} <= set(m)
    # the recall logged is the official scoring of the est.log files the stage wrote, over the pairs it evaluated
    from pcrcg.evaluation.metrics import load_estimates, score_benchmark

    gt = load_benchmark(Layout(layout).benchmark_dir("3DMatch"))
    est, _ = load_estimates(tmp_path / "eval" / "fpfh" / "3DMatch", gt.keys())
    done = {}
    for s, g in gt.items():
        idx = [k for k, p in enumerate(g.pairs) if (p.i, p.j) in est.get(s, {})]
        done[s] = SceneGT(s, tuple(g.pairs[k] for k in idx), g.transforms[idx], g.infos[idx])
    assert sum(len(g.pairs) for g in done.values()) == 3
    assert m["3DMatch/rr"] == pytest.approx(score_benchmark(done, est).rr, abs=1e-9)
    assert res["protocol"]["3DMatch"]["ransac"]["max_iterations"] == 5000
    assert (tmp_path / "eval" / "metrics.json").is_file()
    assert all(Path(p).exists() for p, _ in res["artifacts"])


# --------------------------------------------------------------------------- evaluate_model_outputs


def test_evaluate_model_outputs_on_simulated_network_outputs(tmp_path):
    rng = np.random.default_rng(0)
    pts, cols = box_room(rng, 40000)
    pairs, outputs = [], []
    for k, (i, j) in enumerate([(0, 2), (0, 3), (1, 2), (1, 4)]):
        fp = make_fragment_pair(rng, pts, cols, crop=0.25, voxel=0.04)
        fourier = (rng.normal(scale=1 / 0.06, size=(32, 3)), rng.uniform(0, 6.28, 32))
        noise = 0.3 if k < 3 else 5.0  # the last pair's descriptors are useless
        src = simulate_outputs(rng, fp.src_world, fp.src_overlap, noise, fourier=fourier)
        tgt = simulate_outputs(rng, fp.tgt_world, np.ones(len(fp.tgt_world), bool), noise, fourier=fourier)
        pairs.append((PairRecord("room", i, j, fp.transform, n_fragments=5), information_matrix(fp.src_points[fp.src_overlap])))
        outputs.append(SimpleNamespace(scene="room", i=i, j=j, color_coverage=0.5,
                                       src=SimpleNamespace(points=fp.src_points, descriptors=src[0], overlap=src[1], matchability=src[2]),
                                       tgt=SimpleNamespace(points=fp.tgt_points, descriptors=tgt[0], overlap=tgt[1], matchability=tgt[2])))
    gt = {"room": SceneGT("room", tuple(p for p, _ in pairs), np.stack([p.transform for p, _ in pairs]),
                          np.stack([m for _, m in pairs]))}
    cfg = RegistrationConfig(n_points=(1000, 250), ransac=RansacConfig(max_iterations=10000))
    m = evaluate_model_outputs(outputs, gt, cfg=cfg, est_dir=tmp_path / "est", seed=0, progress=False)
    # (1, 2) is adjacent: 3 counted pairs, the last one fails
    assert m["rr_1000"] == pytest.approx(200 / 3) and m["rr_250"] == pytest.approx(200 / 3)
    assert m["ir_1000"] > 20.0 and m["fmr_1000"] == 75.0
    assert m["rre"] == m["rre_1000"] < 5.0 and m["rte"] < 0.2
    assert m["color_coverage"] == 0.5 and m["n_counted"] == 3
    for n in (1000, 250):
        assert len(read_estimates(tmp_path / "est" / str(n) / "room" / "est.log")) == 4
    # a pair without output counts as a failure; only_evaluated scores the given ones only
    m2 = evaluate_model_outputs(outputs[:1], gt, cfg=cfg, progress=False)
    assert m2["rr_1000"] == pytest.approx(100 / 3)
    m3 = evaluate_model_outputs(outputs[:1], gt, cfg=cfg, only_evaluated=True, progress=False)
    assert m3["rr_1000"] == 100.0 and m3["n_counted"] == 1
    with pytest.raises(KeyError, match="not in the benchmark"):
        evaluate_model_outputs([SimpleNamespace(scene="room", i=7, j=9, src=None, tgt=None)], gt, cfg=cfg, progress=False)


def test_registration_settings_follow_the_profile_and_run_eval_overrides():
    from pcrcg.evaluation.stage import configs_from

    rcfg, bcfg = configs_from(_compose([]))
    assert rcfg.ransac.max_iterations == 10000 and rcfg.n_points == (5000, 2500, 1000, 500, 250)
    rcfg, bcfg = configs_from(_compose([], profile="paper"))
    assert rcfg.ransac.max_iterations == 50000 and rcfg.n_points == (5000, 2500, 1000, 500, 250)
    assert rcfg.ransac.distance == 0.05 and rcfg.ransac.edge_length == 0.9 and rcfg.ransac.ransac_n == 3
    assert bcfg.ransac.max_iterations == 50000 and bcfg.fpfh.voxel == 0.025 and bcfg.fpfh.distance == 2.0  # the model's voxel
    # the run config's eval node wins (conf/run.yaml)
    run_like = OmegaConf.create({"eval": {"n_points": [500], "ransac_iterations": 123, "ransac_distance": 0.04}})
    rcfg, _ = configs_from(run_like)
    assert rcfg.n_points == (500,) and rcfg.ransac.max_iterations == 123 and rcfg.ransac.distance == 0.04
    with pytest.raises(ConfigError, match="sampling"):
        configs_from(OmegaConf.create({"registration": {"sampling": "best"}}))


def _fake_predictions(root: Path, noise: float = 0.3):
    """A stand-in for pcrcg.models.predict.predict_benchmark: simulated outputs on the layout's
    fragments (descriptors of positions in fragment 0's frame, chained through adjacent pairs)."""
    from pcrcg.data.layout import read_cloud
    from pcrcg.geometry import transform_points

    lay = Layout(root)
    gt = load_benchmark(lay.benchmark_dir("3DMatch"))["room"]
    to0 = {0: np.eye(4)}
    for p in gt.pairs:
        if p.j == p.i + 1 and p.i in to0:
            to0[p.j] = to0[p.i] @ p.transform
    rng = np.random.default_rng(0)
    fourier = (rng.normal(scale=1 / 0.06, size=(32, 3)), rng.uniform(0, 6.28, 32))

    def frag(f):
        pts, _ = read_cloud(lay.fragment("room", f))
        d, o, m = simulate_outputs(rng, transform_points(to0[f], pts.astype(np.float64)), np.ones(len(pts), bool),
                                   noise, fourier=fourier)
        return SimpleNamespace(points=pts, descriptors=d, overlap=o, matchability=m)

    calls = []

    def predict_benchmark(cfg, data_root, checkpoint, benchmark, device="cpu", max_pairs=None, progress=True):
        calls.append((str(checkpoint), benchmark, max_pairs))
        for s, g in load_benchmark(Layout(data_root).benchmark_dir(benchmark)).items():
            for p in g.pairs:
                yield SimpleNamespace(scene=s, i=p.i, j=p.j, src=frag(p.j), tgt=frag(p.i), color_coverage=0.8)

    return predict_benchmark, calls


def test_pipeline_evaluate_stage_learned_and_icp_from_learned(layout, tmp_path, monkeypatch):
    import sys as _sys

    from pcrcg.evaluation.stage import evaluate

    fake, calls = _fake_predictions(layout)
    monkeypatch.setitem(_sys.modules, "pcrcg.models.predict", SimpleNamespace(predict_benchmark=fake))
    ckpt = tmp_path / "model.ckpt"
    ckpt.write_bytes(b"x")
    base = {"seed": 0, "views": 2, "eval": {"benchmarks": ["3DMatch", "3DLoMatch"], "n_points": [1000, 250],
                                          "ransac_iterations": 5000, "max_pairs": None}}
    res = evaluate(OmegaConf.create({**base, "method": "learned", "icp_init": "identity"}), data_root=layout,
                   checkpoint=ckpt, out_dir=tmp_path / "learned", progress=False)
    m = res["metrics"]
    for b in ("3DMatch", "3DLoMatch"):
        for n in (1000, 250):
            assert {f"{b}/rr_{n}", f"{b}/fmr_{n}", f"{b}/ir_{n}", f"{b}/rre_{n}", f"{b}/rte_{n}"} <= set(m)
        assert m[f"{b}/rre"] == m[f"{b}/rre_1000"]
    assert m["3DMatch/rr_1000"] == 100.0 and m["3DMatch/fmr_1000"] == 100.0
    assert m["color_coverage"] == pytest.approx(0.8) and m["3DLoMatch/color_coverage"] == pytest.approx(0.8)
    assert res["protocol"]["3DMatch"]["pairs_counted_in_rr"] == 3
    assert len(read_estimates(tmp_path / "learned" / "learned" / "3DMatch" / "1000" / "room" / "est.log")) == 7
    # ICP started from the learned estimates at the largest N
    res = evaluate(OmegaConf.create({**base, "method": "icp", "icp_init": "learned"}), data_root=layout,
                   checkpoint=ckpt, out_dir=tmp_path / "icp", progress=False)
    assert res["metrics"]["3DMatch/rr"] == 100.0 and res["metrics"]["3DMatch/rte"] < 0.03
    assert calls[-1] == (str(ckpt), "3DLoMatch", None)
    with pytest.raises(DataError, match="checkpoint"):
        evaluate(OmegaConf.create({**base, "method": "learned"}), data_root=layout, checkpoint=tmp_path / "none.ckpt",
                 out_dir=tmp_path / "x", progress=False)


# --------------------------------------------------------------------------- silent nonsense (issue 16)


def test_score_mode_warns_when_no_estimate_matches(layout, tmp_path, capsys):
    bench = Layout(layout).benchmark_dir("3DMatch")
    est = _gt_as_estimates(layout, tmp_path / "est")
    ok = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DMatch'}"])
    assert ok["no_estimate_matched"] is False and ok["warnings"] == [] and ok["matched_pairs"] > 0
    # an empty est.log
    empty = tmp_path / "empty" / "room"
    empty.mkdir(parents=True)
    (empty / "est.log").write_text("")
    out = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={empty.parent}"])
    assert out["no_estimate_matched"] is True and out["rr"] == 0.0
    assert "every est.log is empty" in out["warnings"][0]
    assert "warning: no estimate" in capsys.readouterr().err
    # i and j swapped
    g = load_benchmark(bench)["room"]
    swapped = tmp_path / "swapped" / "room"
    write_gt_log(swapped / "est.log", [PairRecord("room", p.j, p.i, p.transform, n_fragments=p.n_fragments)
                                       for p in g.pairs])
    out = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={swapped.parent}"])
    assert out["no_estimate_matched"] is True and "'j i'" in out["warnings"][0]
    # the other benchmark's estimates
    lo = Layout(layout).benchmark_dir("3DLoMatch")
    if load_benchmark(lo)["room"].pairs:
        out = _run(["mode=score", f"benchmark_dir={bench}", f"estimate_dir={est / '3DLoMatch'}"])
        assert out["no_estimate_matched"] is True and "the wrong one" in out["warnings"][0]


def test_pair_mode_warns_on_few_points_odd_scale_and_far_coordinates(clouds, tmp_path):
    d, pair = clouds
    base = ["mode=pair", "method=icp"]
    # three points: RANSAC's minimum, any transform fits them
    write_ply(tmp_path / "three.ply", pair.src_points[:3])
    out = _run([*base, f"source={tmp_path / 'three.ply'}", f"target={d / 'tgt.ply'}"])
    assert out["few_points"] is True and "too few points" in out["warnings"][0]
    write_ply(tmp_path / "two.ply", pair.src_points[:2])
    with pytest.raises(DataError, match="two.ply.*at least 3"):
        _run([*base, f"source={tmp_path / 'two.ply'}", f"target={d / 'tgt.ply'}"])
    # kilometres instead of metres
    write_ply(tmp_path / "src_km.ply", pair.src_points / 1000.0)
    write_ply(tmp_path / "tgt_km.ply", pair.tgt_points / 1000.0)
    out = _run([*base, f"source={tmp_path / 'src_km.ply'}", f"target={tmp_path / 'tgt_km.ply'}"])
    assert out["scale_suspect"] is True and any("units km or mm" in w for w in out["warnings"])
    # UTM-like coordinates: float32 would lose ~0.25 m; the clouds are shifted and the transform shifted back
    off = np.array([500000.0, 4649776.0, 120.0])
    np.savez(tmp_path / "src_utm.npz", points=pair.src_points.astype(np.float64) + off)
    np.savez(tmp_path / "tgt_utm.npz", points=pair.tgt_points.astype(np.float64) + off)
    T_local = np.loadtxt(d / "init.txt")
    S, Si = np.eye(4), np.eye(4)
    S[:3, 3], Si[:3, 3] = -off, off
    write_matrix(tmp_path / "init_utm.txt", Si @ T_local @ S)
    far = _run([*base, f"source={tmp_path / 'src_utm.npz'}", f"target={tmp_path / 'tgt_utm.npz'}",
                f"init={tmp_path / 'init_utm.txt'}"])
    near = _run([*base, f"source={d / 'src.ply'}", f"target={d / 'tgt.ply'}", f"init={d / 'init.txt'}"])
    assert far["origin_shift"] is not None and any("float32" in w for w in far["warnings"])
    assert near["origin_shift"] is None and near["warnings"] == [] and near["few_points"] is False
    T_far = S @ np.array(far["transform"]) @ Si  # back in the local frame
    assert rotation_error_deg(T_far[:3, :3], pair.transform[:3, :3]) < 1.0
    assert np.linalg.norm(T_far[:3, 3] - pair.transform[:3, 3]) < 0.02


def test_metrics_json_holds_no_bare_nan(tmp_path):
    from pcrcg.cli import strict_json

    text = strict_json({"3DMatch/rre": float("nan"), "x": [np.float32(1.5), float("inf")], "n": np.int64(3)})
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"3DMatch/rre": None, "x": [1.5, None], "n": 3}


def test_a_benchmark_tool_given_a_missing_checkpoint_says_so_in_one_line(tmp_path):
    missing = tmp_path / "nowhere" / "model.ckpt"
    proc = subprocess.run([sys.executable, "-m", "pcrcg.benchmarks.evaluation", str(missing)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pcrcg.benchmarks.evaluation: error: ") and str(missing) in lines[0]
