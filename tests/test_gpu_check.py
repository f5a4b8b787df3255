"""The lent GPU's check (pcrcg.benchmarks.gpu_check): its commands, and what it rests on: a run needs neither
Open3D nor MLflow nor kornia (the device image has none of them and Open3D's wheel exceeds what a call carries).
The check itself runs on the CPU in tests/test_predator.py (slow)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from pcrcg.benchmarks.gpu_check import paper_sized_overrides, run_commands, summary

REPO = Path(__file__).resolve().parents[1]


def test_paper_sizes_come_from_the_paper_profile():
    from omegaconf import OmegaConf

    from pcrcg.config import load_run_config

    paper = OmegaConf.to_container(load_run_config(["profile=paper"]).profile, resolve=True)
    geo = paper_sized_overrides(False)
    assert f"profile.model.voxel_size={paper['model']['voxel_size']}" in geo
    assert f"profile.model.first_dim={paper['model']['first_dim']}" in geo
    assert not any(o.startswith("profile.encoder2d.") for o in geo)
    color = paper_sized_overrides(True)
    assert f"profile.encoder2d.arch={json.dumps(paper['encoder2d']['arch'])}" in color
    # each override applies to a run of another profile
    cfg = load_run_config(["profile=tiny", "features=deep", "projection=implicit", *color])
    assert cfg.profile.model.num_layers == paper["model"]["num_layers"]
    assert list(cfg.profile.encoder2d.decoder_channels) == paper["encoder2d"]["decoder_channels"]


def test_the_runs_use_the_device_and_keep_no_store(tmp_path):
    gpu = run_commands(tmp_path, "cuda", 150, 20, tmp_path / "data")
    cpu = run_commands(tmp_path, "cpu", 2, 2, tmp_path / "data")
    assert set(gpu) == {"predator", "pcrcg"}
    for argv in gpu.values():
        assert "trainer=gpu" in argv and "runtime.device=cuda" in argv and "logger=none" in argv
        assert "profile.train.max_steps=150" in argv and "eval.max_pairs=20" in argv
    assert not any("trainer=gpu" in a for argv in cpu.values() for a in argv)
    assert "features=deep" in gpu["pcrcg"] and "features=none" in gpu["predator"]


def test_summary_of_a_check_without_data():
    res = {"environment": {"python": "3.12", "torch": "2.11", "cuda": True, "gpu": "H100", "gpu_memory_gb": 79.2,
                           "cuda_version": "13.0"}, "device": "cuda", "steps": 150, "eval_pairs": 20,
           "model": {"error": "data/synthmatch-tiny: no data set"},
           "run": {"error": "data/synthmatch-tiny: no data set"}}
    text = summary(res)
    assert "H100 (79.2 GB)" in text and "* runs: data/synthmatch-tiny: no data set" in text


BLOCKER = '''
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("open3d", "mlflow", "kornia"):
            raise ImportError("not on this machine: " + name)
        return None
sys.meta_path.insert(0, _Block())
'''


def test_a_run_needs_neither_open3d_nor_mlflow_nor_kornia(tiny_root, tmp_path):
    """What the GPU check rests on: the main job at the tiny profile (training, the explicit projection with
    SIFT windows, evaluation) where none of the three can be imported."""
    (tmp_path / "block").mkdir()
    (tmp_path / "block" / "sitecustomize.py").write_text(BLOCKER)
    argv = [sys.executable, "-m", "pcrcg.run", "profile=tiny", f"data.root={tiny_root}", "logger=none",
            "features=rgb", "projection=explicit", "matcher2d=sift", "profile.train.max_steps=2", "eval.max_pairs=2",
            f"paths.checkpoints={tmp_path / 'ck'}", f"hydra.run.dir={tmp_path / 'out'}",
            "runtime.report_on_end=false", "trainer.progress_bar=false"]
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(tmp_path / "block"), "HOME": str(tmp_path)}
    check = subprocess.run([sys.executable, "-c", "import open3d"], env=env, capture_output=True, text=True)
    assert "not on this machine: open3d" in check.stderr  # the blocker works
    res = subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    status = json.loads((tmp_path / "out" / "pcrcg_status.json").read_text())
    assert status["status"] == "finished" and status["tracking_uri"] is None
    assert (tmp_path / "out" / "timings.json").is_file()


@pytest.mark.parametrize("bad", [["--skip", "tests,gpu"], ["--steps", "0"]])
def test_bad_arguments_are_one_line(bad):
    from pcrcg.benchmarks.gpu_check import main

    with pytest.raises(SystemExit, match="--skip: unknown step|--steps and --eval-pairs"):
        main(bad)
