"""`python -m pcrcg.evaluate mode=benchmark method=learned checkpoint=FILE data.root=DIR`: a trained
model on every test benchmark of a data set in the layout (here a small partial release, whose
fragments' views a color model reads), evaluated by the pipeline's own code."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO, compose
from pcrcg.data.dataset import benchmark_pairs
from pcrcg.data.layout import Layout, write_pairs
from pcrcg.data.materialise import prepare_dataset
from pcrcg.errors import DataError
from pcrcg.evaluation import read_estimates
from test_data_release import _fake_release, _release_cfg

N_POINTS = "registration.n_points=[300,100]"


@pytest.fixture(scope="module")
def release_root(tmp_path_factory) -> Path:
    """A partial release (1 scene, 4 fragments: 2 read, 2 fused) with both benchmarks."""
    tmp = tmp_path_factory.mktemp("release")
    fragments, rgbd, bench = _fake_release(tmp, missing_frame=None)
    return prepare_dataset(_release_cfg(tmp / "data", fragments, rgbd, bench), log=lambda m: None)


@pytest.fixture(scope="module")
def color_checkpoint(release_root, tmp_path_factory) -> Path:
    """A PCR-CG model (rgb lifted from 2 views) trained for 2 steps at the tiny profile, on the
    release's fragments used as training pairs (a copy of the data set with pairs files)."""
    from pcrcg.models.train import train

    tmp = tmp_path_factory.mktemp("train")
    train_root = tmp / "train-data"
    shutil.copytree(release_root, train_root, symlinks=True)
    pairs = benchmark_pairs(Layout(train_root), "3DMatch")
    write_pairs(Layout(train_root).pairs_file("train"), pairs)
    write_pairs(Layout(train_root).pairs_file("val"), pairs[:1])
    cfg = compose("run", ["profile=tiny", "features=rgb", "projection=implicit", "logger=none",
                          f"data.root={train_root}", "trainer.max_steps=2", "trainer.limit_val_batches=1",
                          "trainer.progress_bar=false"])
    res = train(cfg, data_root=train_root, out_dir=tmp / "run", device="cpu")
    return Path(res["checkpoint"])


def _evaluate(overrides: list[str]) -> dict:
    from pcrcg.evaluate import run

    out = run(compose("evaluate", ["profile=tiny", "mode=benchmark", "method=learned", N_POINTS, *overrides]))
    json.dumps(out, allow_nan=False)  # the JSON last line, strict
    return out


def test_learned_model_on_every_benchmark_with_views(release_root, color_checkpoint, tmp_path, capsys):
    out_dir = tmp_path / "eval"
    res = _evaluate([f"checkpoint={color_checkpoint}", f"data.root={release_root}", f"out_dir={out_dir}"])
    assert res["method"] == "learned" and res["checkpoint"] == str(color_checkpoint)
    assert set(res["benchmarks"]) == {"3DMatch", "3DLoMatch"}
    from pcrcg.evaluation.metrics import score_directories

    for b, m in res["benchmarks"].items():
        for n in (300, 100):
            # the recall printed is the official scoring of the est.log files written
            rescored = score_directories(Path(release_root) / "benchmarks" / b, out_dir / b / str(n))
            assert m[f"rr_{n}"] == pytest.approx(rescored.rr, abs=1e-9)
            assert m[f"fmr_{n}"] in (0.0, 25.0, 50.0, 75.0, 100.0) if b == "3DMatch" else m[f"fmr_{n}"] in (0.0, 50.0, 100.0)
    assert res["benchmarks"]["3DMatch"]["n_pairs"] == 4 and res["benchmarks"]["3DLoMatch"]["n_pairs"] == 2
    assert 0.0 < res["color_coverage"] <= 1.0  # the views were read and lifted
    # est.log per benchmark, N and scene; metrics named as a run logs them
    for b, n_pairs in (("3DMatch", 4), ("3DLoMatch", 2)):
        for n in (300, 100):
            assert len(read_estimates(out_dir / b / str(n) / "kitchen" / "est.log")) == n_pairs
    saved = json.loads((out_dir / "metrics.json").read_text())
    assert {"3DMatch/rr_300", "3DMatch/fmr_100", "3DLoMatch/ir_300", "3DMatch/rre", "color_coverage"} <= set(saved["metrics"])
    per = [saved["metrics"][f"{b}/color_coverage"] for b in ("3DMatch", "3DLoMatch")]  # per benchmark, pooled as their mean
    assert saved["metrics"]["color_coverage"] == pytest.approx(sum(per) / 2)
    assert saved["metrics"]["3DMatch/rr_300"] == res["benchmarks"]["3DMatch"]["rr_300"]
    assert saved["benchmarks"]["3DMatch"]["protocol"]["pairs"] == 4
    printed = capsys.readouterr().out
    assert "3DMatch: 4 pairs" in printed and "3DLoMatch: 2 pairs" in printed
    assert len([ln for ln in printed.splitlines() if ln.strip().startswith(("300 ", "100 "))]) == 4


def test_bad_inputs_are_named_before_work(release_root, color_checkpoint, tmp_path):
    from pcrcg.errors import ConfigError

    with pytest.raises(ConfigError, match="checkpoint"):
        _evaluate([f"data.root={release_root}"])
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="junk.ckpt: refused by torch.load\\(weights_only=True\\): not a torch checkpoint"):
        _evaluate([f"checkpoint={junk}", f"data.root={release_root}", f"out_dir={tmp_path / 'x'}"])
    # a color model needs each fragment's views: a missing frame is named before any pair is evaluated
    broken = tmp_path / "broken"
    shutil.copytree(release_root, broken, symlinks=False)
    next((broken / "rgbd" / "kitchen" / "seq-01").glob("frame-000007.color.*")).unlink()
    with pytest.raises(DataError, match="frame-000007.color.png: view of fragment 3 of kitchen is missing"):
        _evaluate([f"checkpoint={color_checkpoint}", f"data.root={broken}", f"out_dir={tmp_path / 'y'}"])
    assert not (tmp_path / "y").exists()


@pytest.mark.parametrize("bad", ["checkpoint", "root"])
def test_cli_errors_are_one_line_exit_2(release_root, tmp_path, bad):
    ckpt = tmp_path / "none.ckpt"
    root = tmp_path / "nowhere" if bad == "root" else release_root
    if bad == "root":
        ckpt.write_bytes(b"x")
    proc = subprocess.run(
        [sys.executable, "-m", "pcrcg.evaluate", "profile=tiny", "mode=benchmark", "method=learned",
         f"checkpoint={ckpt}", f"data.root={root}", f"out_dir={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'hydra'}"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("pcrcg.evaluate: error: ")
    assert (f"{ckpt}: checkpoint does not exist" if bad == "checkpoint" else f"{root}: data root") in lines[0]
