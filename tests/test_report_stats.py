"""Paired bootstrap of recall differences, per-pair outcomes of runs, and the paper's orderings in the report."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR
from pcrcg.data.layout import PairRecord, write_gt_info, write_gt_log
from pcrcg.errors import ConfigError
from pcrcg.evaluation.metrics import (
    SceneGT,
    correspondence_metrics,
    information_matrix,
    load_benchmark,
    score_benchmark,
    write_estimates,
)
from pcrcg.evaluation.pairs import (
    INLIER_RATIO_FILE,
    PAIR_COLUMNS,
    pair_artifacts,
    rows_from_estimate_dir,
    write_inlier_ratios,
)
from pcrcg.geometry import make_transform
from pcrcg.report import generate_report
from pcrcg.report.spec import parse_specs
from pcrcg.report.stats import (
    HOLDS,
    NO_PAPER,
    NOISE,
    PAPER_TIE,
    REVERSED,
    mean_std,
    paired_bootstrap,
    pool_seeds,
    recall,
    verdict,
)

N = (5000, 2500, 1000, 500, 250)
BAD = make_transform(np.eye(3), [1.0, 0.0, 0.0])  # 1 m off: never registered


# --------------------------------------------------------------------------- the statistic and the bootstrap


def _outcomes(rng, sizes=(30, 12, 50), p=0.5):
    scenes = np.concatenate([[f"s{k}"] * n for k, n in enumerate(sizes)])
    return rng.random(len(scenes)) < p, scenes


def test_identical_methods_give_zero_and_an_interval_around_it():
    a, scenes = _outcomes(np.random.default_rng(0))
    iv = paired_bootstrap(a, a.copy(), scenes)
    assert iv.diff == 0.0 and iv.lo <= 0.0 <= iv.hi and not iv.excludes_zero
    assert (iv.n_pairs, iv.n_scenes, iv.n_boot, iv.level) == (92, 3, 2000, 0.95)


def test_thirty_percent_more_registered_pairs_excludes_zero():
    rng = np.random.default_rng(1)
    a, scenes = _outcomes(rng, p=0.4)
    b = a.copy()
    gain = rng.choice(np.flatnonzero(~a), size=int(0.3 * len(a)), replace=False)
    b[gain] = True  # b registers every pair a registers, and 30% of all pairs more
    iv = paired_bootstrap(a, b, scenes)
    assert iv.lo > 0 and iv.excludes_zero and iv.lo < iv.diff < iv.hi
    assert iv.diff == pytest.approx(recall(b, scenes) - recall(a, scenes))
    assert verdict(+6.5, iv) == HOLDS and verdict(-2.2, iv) == REVERSED
    flipped = paired_bootstrap(b, a, scenes)
    assert flipped.hi < 0 and flipped.diff == pytest.approx(-iv.diff)
    assert verdict(+1.0, flipped) == REVERSED and verdict(-1.0, flipped) == HOLDS


def test_point_estimate_is_the_protocols_scene_averaged_recall():
    """Per scene, then the mean over scenes: the same number score_benchmark reports as rr."""
    rng = np.random.default_rng(2)
    gt = _scene_gts(rng, ("a", "b", "c"), (6, 9, 4))
    ok = {s: rng.random(len(g.pairs)) < 0.6 for s, g in gt.items()}
    est = _estimates(gt, ok)
    score = score_benchmark(gt, est)
    counted = [(s, k) for s, g in gt.items() for k, p in enumerate(g.pairs) if p.j - p.i > 1]
    outcomes = np.array([ok[s][k] for s, k in counted], dtype=float)
    scenes = [s for s, _ in counted]
    assert recall(outcomes, scenes) == pytest.approx(score.rr, abs=1e-9)
    assert recall(outcomes, scenes, scene_average=False) == pytest.approx(score.rr_pair, abs=1e-9)
    assert score.rr != pytest.approx(score.rr_pair)  # unequal scenes: the two recalls differ
    iv = paired_bootstrap(np.zeros_like(outcomes), outcomes, scenes)
    assert iv.diff == pytest.approx(score.rr, abs=1e-9)


def test_fixed_seed_gives_the_same_interval_and_another_seed_another():
    rng = np.random.default_rng(3)
    a, scenes = _outcomes(rng)
    b, _ = _outcomes(rng)
    one, two = paired_bootstrap(a, b, scenes, seed=7), paired_bootstrap(a, b, scenes, seed=7)
    assert (one.lo, one.hi) == (two.lo, two.hi)
    other = paired_bootstrap(a, b, scenes, seed=8)
    assert (other.lo, other.hi) != (one.lo, one.hi) and other.diff == one.diff
    wide = paired_bootstrap(a, b, scenes, seed=7, level=0.99)
    assert wide.lo <= one.lo and wide.hi >= one.hi


def test_seeds_are_pooled_per_pair_and_the_point_is_the_mean_over_seeds():
    rng = np.random.default_rng(4)
    _, scenes = _outcomes(rng)
    a = rng.random((3, len(scenes))) < 0.5
    b = rng.random((2, len(scenes))) < 0.7
    iv = paired_bootstrap(a, b, scenes)
    mean_b = np.mean([recall(x, scenes) for x in b])
    mean_a = np.mean([recall(x, scenes) for x in a])
    assert iv.diff == pytest.approx(mean_b - mean_a)
    assert pool_seeds(a) == pytest.approx(a.mean(0))
    assert mean_std([1.0, 3.0]) == (2.0, pytest.approx(np.sqrt(2)), 2)
    assert mean_std([5.0]) == (5.0, 0.0, 1)


def test_seeds_that_disagree_widen_the_resampled_interval_and_agreeing_seeds_keep_it():
    """seeds="resample": seeds drawn seed against seed, then pairs. Seed 0 of b registers 30% more pairs than
    a's seed 0, seed 1 of b 10% fewer than a's seed 1: pooled, +10% looks resolved on 500 pairs; resampled,
    the all-seed-1 draws reach below 0 and it is not."""
    rng = np.random.default_rng(5)
    _, scenes = _outcomes(rng, sizes=(200, 300))
    a = (rng.random((2, len(scenes))) < 0.4)
    b = a.copy()
    b[0, rng.choice(np.flatnonzero(~a[0]), size=150, replace=False)] = True  # seed 0: +30% of the pairs
    b[1, rng.choice(np.flatnonzero(a[1]), size=50, replace=False)] = False  # seed 1: -10%
    pooled = paired_bootstrap(a, b, scenes, seeds="pool")
    resampled = paired_bootstrap(a, b, scenes, seeds="resample")
    assert pooled.diff == pytest.approx(resampled.diff) and pooled.excludes_zero and pooled.lo > 0
    assert resampled.lo < 0 < resampled.hi and (resampled.n_seeds, resampled.seed_mode) == (2, "resample")
    assert (pooled.n_seeds, pooled.seed_mode) == (2, "pool")
    # seeds that agree: resolved either way
    c = a.copy()
    for k in (0, 1):
        c[k, rng.choice(np.flatnonzero(~a[k]), size=100, replace=False)] = True
    agree = paired_bootstrap(a, c, scenes, seeds="resample")
    assert agree.lo > 0 and agree.seed_mode == "resample"
    # one seed, or seeds that are not matched (different counts): the plain pair bootstrap, the same replicates
    one = paired_bootstrap(a[:1], b[:1], scenes, seeds="resample")
    plain = paired_bootstrap(a[0], b[0], scenes)
    assert (one.lo, one.hi, one.seed_mode) == (plain.lo, plain.hi, "pool")
    uneven = paired_bootstrap(a, b[:1], scenes, seeds="resample")
    assert uneven.seed_mode == "pool" and uneven.n_seeds == 1
    with pytest.raises(ValueError, match="seeds must be one of"):
        paired_bootstrap(a, b, scenes, seeds="both")


def test_a_bad_seeds_setting_is_one_line_naming_it():
    from pcrcg.errors import ConfigError
    from pcrcg.report.orderings import StatsSettings

    assert StatsSettings.from_dict({}).seeds == "resample" and StatsSettings.from_dict({"seeds": "pool"}).seeds == "pool"
    with pytest.raises(ConfigError, match="stats.seeds"):
        StatsSettings.from_dict({"seeds": "bootstrap"})


def test_verdicts_without_an_ordering_and_bad_input():
    a, scenes = _outcomes(np.random.default_rng(5))
    iv = paired_bootstrap(a, a, scenes)
    assert verdict(None, iv) == NO_PAPER and verdict(0.0, iv) == PAPER_TIE and verdict(1.0, iv) == NOISE
    assert verdict(1.0, None) is None
    with pytest.raises(ValueError, match="shape"):
        paired_bootstrap(a[:-1], a, scenes)
    with pytest.raises(ValueError, match="level"):
        paired_bootstrap(a, a, scenes, level=95)


def test_compare_specs_name_rows_and_fail_clearly():
    raw = OmegaConf.load(CONF_DIR / "report.yaml")
    raw.pop("hydra")
    raw = OmegaConf.to_container(raw, resolve=True)
    specs = parse_specs(raw["specs"])
    assert [c.text for c in specs["window_size"].compare] == [
        "PCR-CG 7x7 − PCR-CG 3x3", "PCR-CG 11x11 − PCR-CG 7x7", "PCR-CG 17x17 − PCR-CG 11x11"]
    assert [c.text for c in specs["main_results"].compare][0] == "PCR-CG − Predator (geometry only)"
    assert "ICP: improved − original" in [c.text for c in specs["icp_init"].compare]
    proj = [c.text for c in specs["projection"].compare]
    assert len(proj) == 7 and not specs["rre_rte"].compare  # explicit - implicit for each of the 7 lifted features
    assert all(" − " in t and t.split(" − ")[0].split("/")[-1].startswith("explicit") for t in proj)
    assert any("LightGlue matches" in t for t in proj)
    assert raw["stats"]["n_boot"] == 2000
    bad = {"t": {"rows": [{"method": "A", "where": {"x": 1}}], "columns": [{"benchmark": "3DMatch", "metric": "RR"}],
                 "compare": {"pairs": [["A", "B"]]}}}
    with pytest.raises(ConfigError, match="specs.t.compare.pairs"):
        parse_specs(bad)


# --------------------------------------------------------------------------- per-pair outcomes


def _scene_gts(rng, scenes=("kitchen", "office"), n_frags=(10, 10)) -> dict[str, SceneGT]:
    out = {}
    for s, n in zip(scenes, n_frags):
        recs, infos = [], []
        for i in range(n):
            for j in range(i + 1, n):
                R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
                R *= np.sign(np.linalg.det(R))
                recs.append(PairRecord(s, i, j, make_transform(R, rng.normal(size=3)), n_fragments=n))
                infos.append(information_matrix(rng.uniform(-1, 1, size=(50, 3))))
        out[s] = SceneGT(s, tuple(recs), np.stack([r.transform for r in recs]), np.stack(infos))
    return out


def _write_gt(root: Path, bench: str, gt: dict[str, SceneGT]) -> None:
    for s, g in gt.items():
        d = root / "benchmarks" / bench / s
        write_gt_log(d / "gt.log", g.pairs)
        write_gt_info(d / "gt.info", g.pairs, list(g.infos))


def _estimates(gt, ok):
    return {s: {(p.i, p.j): p.transform if ok[s][k] else p.transform @ BAD for k, p in enumerate(g.pairs)}
            for s, g in gt.items()}


def test_pair_rows_from_estimates_reproduce_the_metrics(tmp_path):
    rng = np.random.default_rng(6)
    gt = _scene_gts(rng)
    est_dir = tmp_path / "est" / "3DLoMatch"
    want = {}
    for n in (5000, 250):
        ok = {s: rng.random(len(g.pairs)) < 0.5 for s, g in gt.items()}
        irs = {s: {(p.i, p.j): float(rng.random() * 0.1) for p in g.pairs} for s, g in gt.items()}
        est = _estimates(gt, ok)
        for s, g in gt.items():
            write_estimates(est_dir / str(n) / s / "est.log", g, est[s])
            write_inlier_ratios(est_dir / str(n) / s / INLIER_RATIO_FILE, g, irs[s])
        want[n] = (score_benchmark(gt, est).rr,
                   correspondence_metrics({s: [irs[s][(p.i, p.j)] for p in g.pairs] for s, g in gt.items()})["fmr"])
    logged = pair_artifacts(tmp_path / "eval", {"3DLoMatch": gt}, [(est_dir, "estimates/3DLoMatch"), (tmp_path, "x")])
    assert logged == [(tmp_path / "eval" / "pairs", "pairs")]
    df = pd.read_csv(tmp_path / "eval" / "pairs" / "3DLoMatch.csv")
    assert tuple(df.columns) == PAIR_COLUMNS and len(df) == 2 * 90
    assert (df.groupby("n_points").size() == 90).all()
    for n, (rr, fmr) in want.items():
        sel = df[df["n_points"] == n]
        c = sel[sel["counted"] == 1]
        assert recall(c["registered"].to_numpy(), c["scene"]) == pytest.approx(rr)
        assert recall((sel["inlier_ratio"] > 0.05).to_numpy(), sel["scene"]) == pytest.approx(fmr)
        assert (c["counted"] == 1).sum() == 2 * 36  # j - i > 1
    assert df["error"].notna().all() and (df.loc[df["registered"] == 1, "rte"] < 1e-6).all()
    # the same estimates give the same bytes; a classical method's folder has no <N>/ level
    again = pair_artifacts(tmp_path / "again", {"3DLoMatch": gt}, [(est_dir, "estimates/3DLoMatch")])
    assert (again[0][0] / "3DLoMatch.csv").read_bytes() == (tmp_path / "eval" / "pairs" / "3DLoMatch.csv").read_bytes()
    rows = rows_from_estimate_dir(gt, est_dir / "250")
    assert len(rows) == 90 and {r["n_points"] for r in rows} == {""} and {r["inlier_ratio"] != "" for r in rows} == {True}
    # a broken folder never fails the run: no file, a warning
    assert pair_artifacts(tmp_path / "broken", {"3DLoMatch": gt}, [(tmp_path / "nowhere", "estimates/3DLoMatch")]) == []


def test_evaluate_model_outputs_writes_the_per_pair_inlier_ratios(tmp_path):
    from pcrcg.evaluation import evaluate_model_outputs
    from pcrcg.registration import RansacConfig, RegistrationConfig
    from pcrcg.testing.pairs import make_fragment_pair, simulate_outputs
    from pcrcg.testing.rooms import box_room

    rng = np.random.default_rng(0)
    pts, cols = box_room(rng, 20000)
    recs, infos, outputs = [], [], []
    for k, (i, j) in enumerate([(0, 2), (0, 3), (1, 3)]):
        fp = make_fragment_pair(rng, pts, cols, crop=0.25, voxel=0.05)
        fourier = (rng.normal(scale=1 / 0.06, size=(16, 3)), rng.uniform(0, 6.28, 16))
        noise = 0.3 if k < 2 else 5.0
        src = simulate_outputs(rng, fp.src_world, fp.src_overlap, noise, fourier=fourier)
        tgt = simulate_outputs(rng, fp.tgt_world, np.ones(len(fp.tgt_world), bool), noise, fourier=fourier)
        recs.append(PairRecord("room", i, j, fp.transform, n_fragments=4))
        infos.append(information_matrix(fp.src_points[fp.src_overlap]))
        outputs.append(SimpleNamespace(scene="room", i=i, j=j, src=SimpleNamespace(
            points=fp.src_points, descriptors=src[0], overlap=src[1], matchability=src[2]), tgt=SimpleNamespace(
            points=fp.tgt_points, descriptors=tgt[0], overlap=tgt[1], matchability=tgt[2])))
    gt = {"room": SceneGT("room", tuple(recs), np.stack([r.transform for r in recs]), np.stack(infos))}
    cfg = RegistrationConfig(n_points=(500,), ransac=RansacConfig(max_iterations=2000))
    m = evaluate_model_outputs(outputs, gt, cfg=cfg, est_dir=tmp_path / "est", progress=False)
    assert (tmp_path / "est" / "500" / "room" / INLIER_RATIO_FILE).is_file()
    df = pd.DataFrame(rows_from_estimate_dir(gt, tmp_path / "est"))
    ir = pd.to_numeric(df["inlier_ratio"])
    assert len(df) == 3 and ir.notna().all()
    assert 100 * ir.mean() == pytest.approx(m["ir_500"], abs=1e-3)
    assert 100 * (ir > 0.05).mean() == pytest.approx(m["fmr_500"])
    assert 100 * df["registered"].mean() == pytest.approx(m["rr_500"])


def test_own_estimates_are_scored_beside_the_n_and_recomputed_for_older_files(tmp_path):
    """GeoTransformer's LGR (``estimates/<b>/lgr``): rows with ``estimate`` = lgr and no N; a pairs file
    written before the column (no LGR rows) is completed from the est.log files, on the run's own data
    and on another data set named by its ``<prefix>.data_root`` tag."""
    from pcrcg.report.outcomes import OutcomeSource, parse_key
    from pcrcg.report.sampling import regime_table
    from pcrcg.tracking.store import ensure_store
    from pcrcg.tracking.tracker import RunTracker

    rng = np.random.default_rng(8)
    gt = _scene_gts(rng)
    _write_gt(tmp_path / "data" / "bench", "3DLoMatch", gt)
    _write_gt(tmp_path / "real", "3DLoMatch", gt)
    est_dir = tmp_path / "run" / "estimates" / "3DLoMatch"
    ok = {k: {s: rng.random(len(g.pairs)) < p for s, g in gt.items()}
          for k, p in (("5000", 0.2), ("lgr", 0.6), ("lgr_ransac", 0.4))}
    for k, o in ok.items():
        est = _estimates(gt, o)
        for s, g in gt.items():
            write_estimates(est_dir / k / s / "est.log", g, est[s])
            write_estimates(tmp_path / "real-est" / "3DLoMatch" / k / s / "est.log", g, est[s])
    rr = {k: score_benchmark(gt, _estimates(gt, o)).rr for k, o in ok.items()}
    assert len({round(v, 6) for v in rr.values()}) == 3
    rows = pd.DataFrame(rows_from_estimate_dir(gt, est_dir))
    assert rows.groupby("estimate", sort=True).size().to_dict() == {"": 90, "lgr": 90, "lgr_ransac": 90}
    assert (rows.loc[rows["estimate"] != "", "n_points"] == "").all() and (rows.loc[rows["estimate"] == "", "n_points"] == 5000).all()
    assert [r["estimate"] for r in rows_from_estimate_dir(gt, est_dir, only="lgr")] == ["lgr"] * 90
    assert rows_from_estimate_dir(gt, est_dir / "5000", only="lgr") == []
    assert parse_key("3DMatch/rr_lgr_ransac") == ("3DMatch", "RR", "lgr_ransac") and parse_key("3DMatch/rr_lgrx") is None

    # the sample-size table ignores the rows without N
    new = pair_artifacts(tmp_path / "new", {"3DLoMatch": gt}, [(est_dir, "estimates/3DLoMatch")])[0][0] / "3DLoMatch.csv"
    points = {(s, i): 20000 for s, g in gt.items() for i in range(10)}
    assert regime_table(pd.read_csv(new, dtype={"scene": str}), points)["n_points"].tolist() == [5000]
    # an older pairs file: no estimate column, no LGR rows
    old = tmp_path / "old" / "pairs"
    old.mkdir(parents=True)
    df = pd.read_csv(new, dtype={"scene": str})
    df[df["estimate"].isna()].drop(columns=["estimate"]).to_csv(old / "3DLoMatch.csv", index=False)

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    tr = RunTracker(uri, "geotransformer")
    ids = {}
    for name, pairs_dir in (("new", new.parent), ("old", old)):
        rid = tr.start(name, {"experiment": "geotransformer", "profile": "cpu",
                              "real.data_root": f"{tmp_path / 'real'} params_hash=abc"})
        tr.log_params(rid, {"data.root": "data/bench", "eval.predator_variant": False, "eval.rmse_threshold": 0.2,
                            "eval.max_pairs": "null", "registration.ransac.score": "overlap"})
        tr.log_artifact(rid, est_dir, "estimates/3DLoMatch")
        tr.log_artifact(rid, pairs_dir, "pairs")
        tr.log_artifact(rid, tmp_path / "real-est" / "3DLoMatch", "real/estimates/3DLoMatch")
        tr.finish(rid)
        ids[name] = rid
    from pcrcg.report.load import load_runs

    runs = load_runs(uri, ["geotransformer"])
    with OutcomeSource(uri, tmp_path, runs) as src:
        for name, rid in ids.items():
            for k in ("5000", "lgr", "lgr_ransac"):
                o = src.outcomes(rid, f"3DLoMatch/rr_{k}", rr[k])
                assert o.values is not None and len(o.values) == 72, (name, k, o.reason)
                assert recall(o.values.to_numpy(), o.values.index.get_level_values("scene")) == pytest.approx(rr[k])
                want = "recomputed from the run's estimates/3DLoMatch/" if (name, k[:3]) == ("old", "lgr") else "the run's pairs"
                assert o.source.startswith(want), (name, k, o.source)
            real = src.outcomes(rid, "real/3DLoMatch/rr_lgr", rr["lgr"])
            assert real.values is not None and str(tmp_path / "real") in real.source
            assert "logged no per-pair outcomes on real" in src.outcomes(rid, "real/3DLoMatch/rr_5000", rr["5000"]).reason
            wrong = src.outcomes(rid, "3DLoMatch/rr_lgr", rr["lgr"] + 1.0)
            assert wrong.values is None and "the run logged" in wrong.reason


# --------------------------------------------------------------------------- a real run through the pipeline


def layout_prepare(ctx):
    """Test stage: the small layout the test wrote (``PCRCG_TEST_LAYOUT``)."""
    return Path(os.environ["PCRCG_TEST_LAYOUT"])


def _report_cfg(out_dir: Path, uri: str, **extra) -> dict:
    raw = OmegaConf.load(CONF_DIR / "report.yaml")
    for key in ("hydra", "defaults"):
        raw.pop(key, None)
    cfg = OmegaConf.to_container(raw, resolve=True)
    cfg.update(out_dir=str(out_dir), tracking_uri=uri, **extra)
    return cfg


def test_a_pipeline_run_logs_its_per_pair_outcomes_and_the_report_uses_them(tmp_path, monkeypatch):
    from mlflow.tracking import MlflowClient

    from pcrcg import run as run_mod
    from pcrcg.testing.layouts import write_layout

    data = write_layout(tmp_path / "data", seed=0, n_fragments=5, voxel=0.05, n_points=6000)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("PCRCG_TEST_LAYOUT", str(data))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    for method in ("icp", "color_icp"):
        monkeypatch.setattr(sys, "argv", [
            "pcrcg.run", "--config-path", str(CONF_DIR), "profile=tiny", f"method={method}", "experiment_name=icp_init",
            f"stages.prepare={__name__}.layout_prepare", "runtime.report_on_end=false", "eval.max_pairs=3",
            f"hydra.run.dir={tmp_path}/outputs/{method}"])
        run_mod.main()
    c = MlflowClient(uri)
    runs = c.search_runs([c.get_experiment_by_name("icp_init").experiment_id])
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    for r in runs:
        assert {a.path for a in c.list_artifacts(r.info.run_id, "pairs")} == {"pairs/3DMatch.csv", "pairs/3DLoMatch.csv"}
        for b in ("3DMatch", "3DLoMatch"):
            df = pd.read_csv(c.download_artifacts(r.info.run_id, f"pairs/{b}.csv", str(tmp_path / r.info.run_id)))
            n_gt = sum(len(g.pairs) for g in load_benchmark(data / "benchmarks" / b).values())
            assert len(df) == min(3, n_gt) and df["present"].all()  # max_pairs: the pairs scored, as the metrics
            assert df["n_points"].isna().all()  # a classical method: one estimate per pair
            counted = df[df["counted"] == 1]
            assert recall(counted["registered"].to_numpy(), counted["scene"]) == pytest.approx(r.data.metrics[f"{b}/rr"])
    result = generate_report(_report_cfg(tmp_path / "reports", uri, tables=["icp_init"]), base_dir=tmp_path)
    lines = [ln for ln in result.tables["icp_init"].orderings if ln.comparison.text == "ColorICP − ICP"]
    assert [ln.where for ln in lines] == ["original 3DMatch RR", "original 3DLoMatch RR",
                                          "improved 3DMatch RR", "improved 3DLoMatch RR"]
    assert all(ln.interval is None and "no run" in ln.reason for ln in lines[2:])  # icp_init=learned did not run
    for ln in lines[:2]:
        assert ln.interval is not None and ln.source == "the run's pairs artifact"
        assert ln.paper_diff == pytest.approx({"3DMatch": 0.7, "3DLoMatch": 0.1}[ln.benchmark])
        assert ln.verdict in (HOLDS, REVERSED, NOISE)
    orderings = pd.read_csv(tmp_path / "reports" / "icp_init_orderings.csv")
    assert set(orderings["comparison"]) >= {"ColorICP − ICP", "ICP: improved − original"}


# --------------------------------------------------------------------------- the report on a constructed store


def _learned_run(tr, work: Path, name: str, params: dict, tags: dict, gts: dict, ok: dict, *,
                 pairs: bool = True, est: bool = True, irs: dict | None = None, bias: float = 0.0) -> str:
    """Log a learned run whose estimates register exactly the pairs ``ok[bench][scene]`` (at every N)."""
    folder = work / name.replace(" ", "_").replace("=", "-")
    metrics, arts = {}, []
    for b, gt in gts.items():
        est_dir = folder / "estimates" / b
        estimates = _estimates(gt, ok[b])
        for n in N:
            for s, g in gt.items():
                write_estimates(est_dir / str(n) / s / "est.log", g, estimates[s])
                if irs is not None:
                    write_inlier_ratios(est_dir / str(n) / s / INLIER_RATIO_FILE, g, irs[b][s])
            metrics[f"{b}/rr_{n}"] = score_benchmark(gt, estimates).rr + bias
            if irs is not None:
                metrics[f"{b}/fmr_{n}"] = correspondence_metrics(
                    {s: [irs[b][s][(p.i, p.j)] for p in g.pairs] for s, g in gt.items()})["fmr"]
        arts.append((est_dir, f"estimates/{b}"))
    rid = tr.start(name, {"experiment": tr.experiment_name, "git_sha": "b" * 40, "profile": "cpu", **tags})
    tr.log_params(rid, {"eval.predator_variant": False, "eval.rmse_threshold": 0.2, "eval.max_pairs": "null",
                        "eval.fmr_threshold": 0.05, "registration.ransac.score": "overlap", **params})
    tr.log_metrics(rid, metrics)
    if est:
        for path, art in arts:
            tr.log_artifact(rid, path, art)
    if pairs:
        for path, art in pair_artifacts(folder, gts, arts):
            tr.log_artifact(rid, path, art)
    tr.finish(rid)
    return rid


def _more(rng, ok: dict[str, np.ndarray], gt: dict[str, SceneGT], frac: float) -> dict[str, np.ndarray]:
    """Every pair ``ok`` registers, plus ``frac`` of the counted pairs more (per scene)."""
    out = {}
    for s, g in gt.items():
        counted = np.array([p.j - p.i > 1 for p in g.pairs])
        free = np.flatnonzero(counted & ~ok[s])
        extra = rng.choice(free, size=min(len(free), int(round(frac * counted.sum()))), replace=False)
        out[s] = ok[s].copy()
        out[s][extra] = True
    return out


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import ensure_store

    root = tmp_path_factory.mktemp("stats")
    uri = f"sqlite:///{root}/mlflow.db"
    ensure_store(uri)
    rng = np.random.default_rng(11)
    gts = {b: _scene_gts(rng) for b in ("3DMatch", "3DLoMatch")}
    for b, gt in gts.items():
        _write_gt(root / "data" / "bench", b, gt)
    base = {b: {s: rng.random(len(g.pairs)) < 0.4 for s, g in gt.items()} for b, gt in gts.items()}
    irs = {b: {s: {(p.i, p.j): float(rng.random() * 0.12) for p in g.pairs} for s, g in gt.items()}
           for b, gt in gts.items()}
    work = root / "work"
    ids: dict = {}

    # main_results, two seeds each: PCR-CG = Predator on 3DMatch, Predator + 30% of the pairs on 3DLoMatch
    tr = RunTracker(uri, "main_results")
    for seed in (0, 1):
        flip = {b: {s: v ^ (rng.random(len(v)) < 0.1) for s, v in base[b].items()} for b in base}
        better = {"3DMatch": flip["3DMatch"], "3DLoMatch": _more(rng, flip["3DLoMatch"], gts["3DLoMatch"], 0.3)}
        for label, ok in (("Predator", flip), ("PCR-CG", better)):
            ids[(label, seed)] = _learned_run(tr, work, f"{label} seed={seed}", {"seed": seed, "encoder2d.name": "pri3d"},
                                              {"label": label, "config_hash": f"{label}{seed}"}, gts, ok, irs=irs)
    lo = {"3DLoMatch": gts["3DLoMatch"]}
    # window_size: 3x3 = 7x7 (7x7 logged before the per-pair file: recomputed from est.log + gt on disk),
    # 11x11 = 7x7 + 30% (paper: +1.6, holds), 17x17 = 11x11 + 30% (paper: -2.2, reversed)
    tr = RunTracker(uri, "window_size")
    w3 = base["3DLoMatch"]
    w11 = _more(rng, w3, lo["3DLoMatch"], 0.3)
    w17 = _more(rng, w11, lo["3DLoMatch"], 0.3)
    for ws, ok, pairs in ((3, w3, True), (7, w3, False), (11, w11, True), (17, w17, True)):
        ids[ws] = _learned_run(tr, work, f"window_size={ws}", {"window_size": ws, "seed": 0, "data.root": "data/bench",
                                                                       "encoder2d.name": "pri3d"},
                               {"label": "PCR-CG", "config_hash": f"w{ws}"}, lo, {"3DLoMatch": ok}, pairs=pairs)
    # views: 1 view logged metrics only; 2 views est.log but its data root is gone; 3 views complete
    tr = RunTracker(uri, "views")
    for v, kw in ((1, {"pairs": False, "est": False}), (2, {"pairs": False}), (3, {})):
        ids[f"v{v}"] = _learned_run(tr, work, f"views={v}", {"views": v, "seed": 0, "data.root": "data/gone",
                                                                    "projection.name": "implicit", "encoder2d.name": "pri3d"},
                                    {"label": "PCR-CG", "config_hash": f"v{v}"}, lo, {"3DLoMatch": w3}, **kw)
    # backbone_2d: ImageNet's logged recall does not match its est.log (benchmark files changed since the run)
    tr = RunTracker(uri, "backbone_2d")
    for enc, kw in (("scratch", {}), ("imagenet", {"pairs": False, "bias": 5.0})):
        ids[enc] = _learned_run(tr, work, f"encoder2d={enc}", {"encoder2d.name": enc, "seed": 0,
                                                               "data.root": "data/bench", "features.name": "deep",
                                                               "encoder2d.training": "detached"},
                                {"label": "PCR-CG", "config_hash": enc}, lo, {"3DLoMatch": w3}, **kw)
    out = root / "reports"
    result = generate_report(_report_cfg(out, uri, profile="cpu"), base_dir=root, command="python -m pcrcg.report")
    return {"root": root, "out": out, "ids": ids, "result": result, "uri": uri}


def _line(report, table, comparison, where):
    hits = [ln for ln in report["result"].tables[table].orderings if ln.comparison.text == comparison and ln.where == where]
    assert len(hits) == 1, [(ln.comparison.text, ln.where) for ln in report["result"].tables[table].orderings]
    return hits[0]


def test_pcrcg_above_predator_holds_on_3dlomatch_and_is_noise_on_3dmatch(report):
    lo = _line(report, "main_results", "PCR-CG − Predator (geometry only)", "3DLoMatch RR 5000")
    assert lo.verdict == HOLDS and lo.interval.lo > 0 and lo.paper_diff == pytest.approx(6.5)
    assert lo.n_seeds == 2 and lo.ours_std is not None and lo.interval.n_pairs == 72 and lo.interval.n_scenes == 2
    # seed against seed (in seed order on both sides), then pairs: stats.seeds=resample, the default
    assert (lo.interval.n_seeds, lo.interval.seed_mode) == (2, "resample")
    from pcrcg.report.orderings import _seed_key

    assert sorted(["10", "b", "2", "0"], key=_seed_key) == ["0", "2", "10", "b"]
    # the pooled point estimate is the difference of the table's means over seeds
    t = report["result"].tables["main_results"]
    cells = {c.row.method: c for c in t.cells if c.col.benchmark == "3DLoMatch" and c.col.metric == "RR"
             and c.col.n_points == 5000}
    assert lo.interval.diff == pytest.approx(cells["PCR-CG"].mean - cells["Predator"].mean)
    mid = _line(report, "main_results", "PCR-CG − Predator (geometry only)", "3DMatch RR mean over N")
    assert mid.verdict == NOISE and mid.interval.diff == 0.0 and mid.interval.lo <= 0 <= mid.interval.hi
    assert mid.paper_diff == pytest.approx(np.mean([89.4, 90.7, 90.0, 88.7, 86.8]) - np.mean([89.0, 89.9, 90.6, 88.5, 86.6]))
    fmr = _line(report, "main_results", "PCR-CG − Predator (geometry only)", "3DMatch FMR 5000")
    assert fmr.interval is not None and fmr.interval.diff == 0.0  # same inlier ratios: same FMR
    assert fmr.source == "the run's pairs artifact"


def test_window_sizes_hold_reverse_and_recompute_older_runs(report):
    same = _line(report, "window_size", "PCR-CG 7x7 − PCR-CG 3x3", "3DLoMatch RR 5000")
    assert same.verdict == NOISE and same.interval.diff == 0.0
    assert same.source.startswith("the run's pairs artifact; recomputed from the run's estimates/3DLoMatch est.log files")
    assert _line(report, "window_size", "PCR-CG 11x11 − PCR-CG 7x7", "3DLoMatch RR 5000").verdict == HOLDS
    rev = _line(report, "window_size", "PCR-CG 17x17 − PCR-CG 11x11", "3DLoMatch RR mean over N")
    assert rev.verdict == REVERSED and rev.interval.lo > 0 and rev.paper_diff < 0


def test_missing_per_pair_outcomes_say_why(report):
    one = _line(report, "views", "2 views − 1 view", "3DLoMatch RR 5000")
    assert one.interval is None and one.verdict is None and one.ours_diff == pytest.approx(0.0)
    assert "logged neither per-pair outcomes (pairs/3DLoMatch.csv) nor est.log files" in one.reason
    two = _line(report, "views", "3 views − 2 views", "3DLoMatch RR 5000")
    assert "benchmark files" in two.reason and "data/gone" in two.reason
    enc = _line(report, "backbone_2d", "ImageNet, detached (official code) − Scratch, detached (official code)", "3DLoMatch RR 5000")
    assert enc.interval is None and "the run logged" in enc.reason and "regenerated" in enc.reason
    # no ordering in the paper (ties) and rows the paper does not have
    tie = _line(report, "backbone_2d", "Pri3D, detached (official code) − ImageNet, detached (official code)", "3DLoMatch RR 5000")
    assert tie.verdict == PAPER_TIE


def test_tables_csv_and_index_show_the_orderings(report):
    out = report["out"]
    md = (out / "window_size.md").read_text()
    assert "**The paper's orderings, tested**" in md
    assert "paired bootstrap 95% interval over the test pairs (2000 resamples of the pairs within each scene, seed 0" in md
    assert "| PCR-CG 17x17 − PCR-CG 11x11 | 3DLoMatch RR 5000 | -2.2 |" in md and "| reversed |" in md
    views = (out / "views.md").read_text()
    assert "| 2 views − 1 view | 3DLoMatch RR 5000 | +1.4 | +0.0 | — | — [" in views
    df = pd.read_csv(out / "main_results_orderings.csv")
    row = df[(df["benchmark"] == "3DLoMatch") & (df["metric"] == "RR") & (df["at"] == "5000")].iloc[0]
    assert row["verdict"] == HOLDS and row["n_boot"] == 2000 and row["ci_low"] > 0 and row["n_seeds"] == 2
    assert row["ci_seeds"] == "resample (2)"
    assert set(row["row_run_ids"].split(";")) == {report["ids"][("PCR-CG", 0)], report["ids"][("PCR-CG", 1)]}
    index = (out / "README.md").read_text()
    assert "| window_size | window_size, main_results | cpu | 4 | 15/30 | 2 / 2 / 2 |" in index
    assert "| views | views, projection | cpu | 3 | 0/14 | 0 / 0 / 0 (4 untested) |" in index
    tex = (out / "window_size.tex").read_text()
    assert "the paper's orderings, tested" in tex and r"PCR-CG 17x17 $-$ PCR-CG 11x11 & 3DLoMatch RR 5000" in tex


def test_reports_are_deterministic(report, tmp_path):
    again = generate_report(_report_cfg(tmp_path / "r", report["uri"], profile="cpu", tables=["window_size"]),
                            base_dir=report["root"])
    assert (tmp_path / "r" / "window_size_orderings.csv").read_bytes() == \
        (report["out"] / "window_size_orderings.csv").read_bytes()
    assert again.tables["window_size"].orderings[0].interval == report["result"].tables["window_size"].orderings[0].interval
