"""Reliability and security (issue 16): no file runs code, no run is left dangling, every bad input is
one line before work, the same seed gives the same bytes.

Each test fails without its change: crafted pickles for every loader (a payload that would create a
marker file), checkpoint files that are not checkpoints, a corrupt ``last.ckpt`` / planted
``model.ckpt``, runs interrupted by Ctrl-C / SIGTERM / SystemExit and by SIGKILL (stale runs), a sweep
interrupted during training (subprocess), a new SQLite store opened by several processes at once,
command-line sweeps checked before the first job, a corrupt frame found before the first training
step, two generations compared file by file, temp folders and pool workers of killed ``prepare``
runs, and one-line errors with exit 2 from every entry point.
"""

from __future__ import annotations

import builtins
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import REPO, tiny_data_cfg
from pcrcg.errors import DataError, Terminated

TESTS = Path(__file__).resolve().parent


# --------------------------------------------------------------------------- crafted files


class _Payload:
    """Unpickling this calls ``open(marker, "w")``: the marker file is the proof that code ran."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (builtins.open, (self.marker, "w"))


def _crafted(path: Path, marker: Path, kind: str) -> Path:
    obj = {"state_dict": {}, "hyper_parameters": {"model": {}}, "x": _Payload(marker)}
    if kind == "torch_zip":
        torch.save(obj, path)
    elif kind == "torch_legacy":
        torch.save(obj, path, _use_new_zipfile_serialization=False)
    elif kind == "pickle2":
        path.write_bytes(pickle.dumps(obj, protocol=2))
    else:  # pickle protocol 5 (framed)
        path.write_bytes(pickle.dumps(obj, protocol=5))
    return path


KINDS = ("torch_zip", "torch_legacy", "pickle2", "pickle5")


def _tiny_module():
    from pcrcg.models.module import PCRCGModule
    from test_training import MODEL

    return PCRCGModule(MODEL)


def _checkpoint(path: Path) -> Path:
    """A valid checkpoint of the project's format, without training."""
    from test_training import MODEL

    m = _tiny_module()
    torch.save({"state_dict": m.state_dict(), "hyper_parameters": {"model": MODEL}, "global_step": 1,
                "optimizer_states": [], "epoch": 0}, path)
    return path


@pytest.mark.parametrize("kind", KINDS)
def test_crafted_pickles_run_no_code_in_any_loader(tmp_path, kind):
    from pcrcg.data.layout import read_cloud
    from pcrcg.models.kpconv.pyramid import PyramidCache
    from pcrcg.models.train import load_module, load_pair_output, read_checkpoint
    from pcrcg.pretrain2d.core import _reusable
    from pcrcg.vision.encoders import ResUNet, load_pri3d_checkpoint, load_torchvision_weights

    marker = tmp_path / "PWNED"
    f = _crafted(tmp_path / "evil.ckpt", marker, kind)
    # trained models: evaluation, pipeline reuse, resume
    for load in (load_module, read_checkpoint):
        with pytest.raises(DataError, match="evil.ckpt"):
            load(f)
    # 2D encoder weights (imagenet / pri3d), the 2D pretraining's own checkpoint
    enc = ResUNet("resnet18", 8)
    with pytest.raises(DataError, match="evil.ckpt"):
        load_torchvision_weights(enc, f)
    with pytest.raises(DataError, match="evil.ckpt"):
        load_pri3d_checkpoint(enc, f)
    assert _reusable(f, "hash") is None  # retrained, not trusted
    # fragments given as Predator's .pth
    pth = f.with_suffix(".pth")
    shutil.copy(f, pth)
    with pytest.raises(DataError, match="evil.pth"):
        read_cloud(pth)
    # caches and hand-over files (.npz with a pickled object array)
    npz = tmp_path / "evil.npz"
    evil = np.array([_Payload(marker)], dtype=object)
    np.savez(npz, key=evil, points_0=evil, scene=evil, points=evil)
    cache = PyramidCache(4, tmp_path)
    shutil.copy(npz, cache._path("k"))
    assert cache._load("k") is None  # rebuilt
    with pytest.raises(ValueError):
        load_pair_output(npz)
    with pytest.raises(DataError, match="evil.npz"):
        read_cloud(npz)
    from pcrcg.vision.matching import MatchCache

    mc = MatchCache(tmp_path / "mc")
    mc.path("abcd").parent.mkdir(parents=True)
    shutil.copy(npz, mc.path("abcd"))
    assert mc.load("abcd") is None
    assert not marker.exists()


def test_checkpoints_that_are_not_checkpoints_are_one_line_errors(tmp_path, monkeypatch, capsys):
    from pcrcg.models.train import load_module

    good = _checkpoint(tmp_path / "good.ckpt")
    loaded = load_module(good, device="cpu")
    saved = torch.load(good, map_location="cpu", weights_only=True)["state_dict"]
    assert all(torch.equal(v, saved[k]) for k, v in loaded.state_dict().items())
    (tmp_path / "text.ckpt").write_text("not a checkpoint\n")
    torch.save(_tiny_module().state_dict(), tmp_path / "bare.ckpt")
    (tmp_path / "cut.ckpt").write_bytes(good.read_bytes()[:2000])
    other = torch.load(good, weights_only=True)
    other["state_dict"] = {k: v for k, v in list(other["state_dict"].items())[1:]}
    torch.save(other, tmp_path / "other.ckpt")
    cases = {"text.ckpt": "not a torch checkpoint", "bare.ckpt": "bare state dict",
             "cut.ckpt": "corrupt or truncated", "other.ckpt": "does not fit the model",
             "evil.ckpt": "would call"}
    _crafted(tmp_path / "evil.ckpt", tmp_path / "PWNED", "torch_zip")
    write_ply = __import__("pcrcg.data.layout", fromlist=["write_ply"]).write_ply
    pts = np.random.default_rng(0).random((500, 3)).astype(np.float32)
    write_ply(tmp_path / "a.ply", pts)
    for name, text in cases.items():
        rc, err = _entry("pcrcg.evaluate", ["profile=tiny", "mode=pair", "method=learned",
                                            f"checkpoint={tmp_path / name}", f"source={tmp_path / 'a.ply'}",
                                            f"target={tmp_path / 'a.ply'}"], tmp_path, monkeypatch, capsys)
        assert rc == 2, (name, err)
        assert len(err.strip().splitlines()) == 1 and name in err and text in err, err
    assert not (tmp_path / "PWNED").exists()


def test_bad_last_ckpt_is_moved_aside_and_training_starts_afresh(tmp_path, capsys):
    from pcrcg.models.train import train
    from test_training import MODEL, trainer_cfg, write_toy_layout

    root = write_toy_layout(tmp_path / "toy")
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=2, max_epochs=1, limit_train_batches=2), "seed": 0,
           "data": {"root": str(root)}}
    ckdir = tmp_path / "run" / "checkpoints"
    ckdir.mkdir(parents=True)
    _crafted(ckdir / "last.ckpt", tmp_path / "PWNED", "torch_zip")
    res = train(cfg, out_dir=tmp_path / "run")
    assert res["metrics"]["train/global_step"] == 2
    assert not (tmp_path / "PWNED").exists()
    aside = list(ckdir.glob("last.ckpt.bad-*"))
    assert len(aside) == 1
    err = capsys.readouterr().err
    assert "cannot resume" in err and "last.ckpt" in err and aside[0].name in err
    # the new last.ckpt reads without the ability to run code, hyper-parameters included
    ck = torch.load(ckdir / "last.ckpt", map_location="cpu", weights_only=True)
    assert ck["hyper_parameters"]["model"]["voxel_size"] == MODEL["voxel_size"] and ck["optimizer_states"]


def test_planted_model_ckpt_is_not_reused(tmp_path, monkeypatch, capsys):
    """``<paths.checkpoints>/<train hash>/model.ckpt`` that does not read safely: moved aside, trained again."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import JobInfo, RunContext, train_key, train_model

    cfg = load_run_config(["profile=tiny", "logger=none", f"paths.checkpoints={tmp_path / 'ck'}"])
    cache = tmp_path / "ck" / train_key(cfg)  # the cache's key: the training config and the code version
    cache.mkdir(parents=True)
    _crafted(cache / "model.ckpt", tmp_path / "PWNED", "torch_zip")
    calls = []

    def fake_train(cfg, data_root=None, out_dir=None, logger=None, device=None):
        calls.append(out_dir)
        return {"checkpoint": str(_checkpoint(tmp_path / "fresh.ckpt")), "history": {"train/loss": [1.0]}}

    monkeypatch.setattr("pcrcg.models.train.train", fake_train)
    job = JobInfo(output_dir=tmp_path / "out", base_dir=tmp_path)
    out = train_model(RunContext(cfg=cfg, job=job, out_dir=tmp_path / "out", device="cpu"))
    assert len(calls) == 1 and not out.reused and out.checkpoint == cache / "model.ckpt"
    assert list(cache.glob("model.ckpt.bad-*")) and "not reusing" in capsys.readouterr().err
    again = train_model(RunContext(cfg=cfg, job=job, out_dir=tmp_path / "out", device="cpu"))
    assert again.reused and len(calls) == 1  # the good one is reused
    assert not (tmp_path / "PWNED").exists()


# --------------------------------------------------------------------------- terminal states


def test_ctrl_c_in_lightning_comes_back_as_keyboard_interrupt(tmp_path):
    from lightning.pytorch.callbacks import Callback

    from pcrcg.models.train import train
    from test_training import MODEL, trainer_cfg, write_toy_layout

    class CtrlC(Callback):
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == 1:
                raise KeyboardInterrupt

    root = write_toy_layout(tmp_path / "toy")
    cfg = {"model": MODEL, "trainer": trainer_cfg(max_steps=3, checkpoint_every_n_steps=100), "seed": 0,
           "data": {"root": str(root)}}
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):  # Lightning alone: SystemExit(1), SIGINT ignored from then on
        train(cfg, out_dir=tmp_path / "run", callbacks=[CtrlC()])
    assert signal.getsignal(signal.SIGINT) is before
    assert torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 1


def _stage_raising(exc: BaseException):
    def stage(ctx):
        raise exc
    return stage


@pytest.mark.parametrize("exc,status,text", [
    (KeyboardInterrupt(), "KILLED", "interrupted (Ctrl-C) during train"),
    (Terminated("SIGTERM"), "KILLED", "terminated (SIGTERM) during train"),
    (SystemExit(3), "FAILED", "SystemExit"),
])
def test_every_path_ends_the_run(tmp_path, monkeypatch, exc, status, text):
    import test_run_support

    from pcrcg.config import load_run_config
    from pcrcg.pipeline import JobInfo, run_job
    from test_run_support import tracked_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setattr(test_run_support, "boom", _stage_raising(exc), raising=False)
    cfg = load_run_config(["profile=tiny", f"logger.tracking_uri={uri}", "stages.prepare=test_run_support.fake_prepare",
                           "stages.train=test_run_support.boom", "stages.evaluate=test_run_support.fake_evaluate",
                           f"paths.data={tmp_path / 'data'}", "runtime.report_on_end=false"])
    with pytest.raises(type(exc)):
        run_job(cfg, JobInfo(output_dir=tmp_path / "out", base_dir=tmp_path))
    (run,) = tracked_runs(uri, "default")
    assert run.info.status == status and text in run.data.tags["error"] + run.data.tags["error_type"]
    assert json.loads((tmp_path / "out" / "pcrcg_status.json").read_text())["status"] in ("killed", "failed")


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_running_runs_are_closed_on_relaunch_and_left_out_of_the_report(tmp_path, monkeypatch):
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import JobInfo, run_job
    from pcrcg.report.load import load_runs
    from pcrcg.tracking.hashing import config_hash, to_plain
    from pcrcg.tracking.tracker import TAG_HASH, TAG_PID, RunTracker, owner_tags
    from test_run_support import tracked_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    cfg = load_run_config(["profile=tiny", f"logger.tracking_uri={uri}", "method=fpfh",
                           "stages.prepare=test_run_support.fake_prepare", "stages.evaluate=test_run_support.fake_evaluate",
                           f"paths.data={tmp_path / 'data'}", "runtime.report_on_end=false"])
    h = config_hash(to_plain(cfg))
    tracker = RunTracker(uri, "default")
    # a run killed outright (its process is gone), one of a live process, one of another config
    dead = tracker.start("dead", {TAG_HASH: h, **{TAG_PID: str(_dead_pid())}})
    alive = tracker.start("alive", {TAG_HASH: h})  # this process: alive
    other = tracker.start("other", {TAG_HASH: "0" * 16, TAG_PID: str(_dead_pid())})
    assert set(load_runs(uri, ["default"])["run_id"]) == {alive}  # the report leaves stale runs out
    assert owner_tags()[TAG_PID] == str(os.getpid())
    tags = tracked_runs(uri, "default")[0].data.tags  # the machine that computed it (runs differ across CPU types)
    assert tags["pcrcg.cpu"] and tags["pcrcg.cpu"] != "unknown" and tags["pcrcg.cpu_capability"] not in ("", "None")
    out = run_job(cfg, JobInfo(output_dir=tmp_path / "out", base_dir=tmp_path))
    assert out.status == "finished"
    runs = {r.info.run_id: r for r in tracked_runs(uri, "default")}
    assert runs[dead].info.status == "KILLED" and runs[dead].data.tags["closed_stale"] == "true"
    assert runs[alive].info.status == "RUNNING" and runs[other].info.status == "RUNNING"  # not ours to close


def _wait_for(predicate, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    t0 = time.time()
    while not predicate():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"the process ended (rc {proc.returncode}) before {what}")
        if time.time() - t0 > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def test_sweep_interrupted_during_training(tiny_root, tmp_path):
    """Ctrl-C during job 1's training: one line, exit 130, the run KILLED; the relaunch finishes both
    jobs (job 1 resumes from its last.ckpt) and nothing is left RUNNING."""
    from test_run_support import tracked_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    env = {**os.environ, "PYTHONPATH": str(TESTS), "MLFLOW_TRACKING_URI": uri, "OMP_NUM_THREADS": "1"}
    args = [sys.executable, "-m", "pcrcg.run", "profile=tiny", f"data.root={tiny_root}",
            "stages.train=reliability_support.slow_train", "stages.evaluate=test_run_support.fake_evaluate",
            f"paths.checkpoints={tmp_path / 'ck'}", "seed=0,1", "runtime.report_on_end=false",
            "trainer.progress_bar=false", f"hydra.sweep.dir={tmp_path / 'multirun'}", "-m"]
    steps = tmp_path / "training_step.txt"
    with open(tmp_path / "err1.txt", "w") as err:
        # SIGINT at its default in the child: an ignored SIGINT (left so by any earlier test of the
        # session, or by the shell CI runs in) is inherited, and Python then keeps ignoring it
        p = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=err,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            # after step 2's periodic last.ckpt (tiny: every 2 steps); a Ctrl-C inside a step saves nothing (the
            # state there is half a step), so the relaunch resumes exactly from step 2 (3: it came after step 3)
            _wait_for(lambda: steps.is_file() and "0 2" in steps.read_text(), 240, "job 1's third step", p)
            p.send_signal(signal.SIGINT)
            rc = p.wait(120)
        finally:
            p.kill()
    err = (tmp_path / "err1.txt").read_text()
    assert rc == 130, err[-3000:]
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "pcrcg.run: interrupted (Ctrl-C)"
    (run,) = tracked_runs(uri, "default")
    assert run.info.status == "KILLED" and "interrupted (Ctrl-C) during train" in run.data.tags["error"]
    assert (tmp_path / "ck" / "seed0" / "checkpoints" / "last.ckpt").is_file()
    n_steps = len(steps.read_text().splitlines())

    r = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    runs = tracked_runs(uri, "default")
    assert sorted(x.info.status for x in runs) == ["FINISHED", "FINISHED", "KILLED"]
    lines = steps.read_text().splitlines()[n_steps:]
    assert lines[0] in ("0 2", "0 3")  # job 1 resumed (from step 2, or 3 if the Ctrl-C came between steps)
    assert any(ln.startswith("1 ") for ln in lines)


# --------------------------------------------------------------------------- several jobs


_OPEN_STORE = """
import sys, time
from pcrcg.tracking.tracker import RunTracker
t = float(sys.argv[2])
while time.time() < t:
    time.sleep(0.005)
tracker = RunTracker(sys.argv[1], "race")
tracker.finish(tracker.start("r", {}))
"""


def test_new_sqlite_store_opened_by_several_processes_at_once(tmp_path):
    uri = f"sqlite:///{tmp_path}/new.db"
    start = time.time() + 6.0  # after both interpreters have imported mlflow
    procs = [subprocess.Popen([sys.executable, "-c", _OPEN_STORE, uri, str(start)], cwd=REPO,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    errs = [p.communicate(timeout=180)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(e[-1500:] for e in errs)
    from test_run_support import tracked_runs

    assert [r.info.status for r in tracked_runs(uri, "race")] == ["FINISHED"] * 2


def test_command_line_sweep_values_are_checked_before_the_first_job(tmp_path, monkeypatch, capsys):
    from test_run_support import FAKES, make_conf, run_cli

    conf = make_conf(tmp_path / "conf")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/mlflow.db")
    def base(*sweep: str) -> list[str]:
        return ["--config-path", str(conf), "profile=tiny", *FAKES, f"hydra.sweep.dir={tmp_path}/multirun",
                "runtime.report_on_end=false", *sweep, "-m"]

    assert run_cli(base("trainer.optim.lr=0.1,abc"), tmp_path, monkeypatch) == 2
    err = capsys.readouterr().err
    assert "invalid config value trainer.optim.lr='abc'" in err and "no job was started" in err
    assert not list(tmp_path.rglob("pcrcg_status.json"))
    assert run_cli(base("profile.train.max_steps=2,0"), tmp_path, monkeypatch) == 2
    assert "profile.train.max_steps=0" in capsys.readouterr().err
    # a plain command-line sweep (no experiment file): the store and the data set are prepared once, first
    assert run_cli(base("trainer.optim.lr=0.1,0.2"), tmp_path, monkeypatch) == 0
    out = capsys.readouterr().out
    assert "data set ready for all jobs" in out and "2 jobs: 2 finished" in out
    assert out.index("data set ready for all jobs") < out.index("[run] finished")


def test_inputs_are_checked_before_the_first_training_step(tiny_root, tmp_path):
    """A truncated color PNG of a test scene: the run stops, naming it, before training starts."""
    from pcrcg.config import load_run_config
    from pcrcg.data.layout import Layout
    from pcrcg.pipeline import JobInfo, run_job

    root = tmp_path / "data"
    shutil.copytree(tiny_root, root)
    layout = Layout(root)
    scene = layout.scenes("test")[0]
    png = sorted((layout.rgbd_dir(scene) / "seq-01").glob("*.color.png"))[3]
    png.write_bytes(png.read_bytes()[:300])
    cfg = load_run_config(["profile=tiny", "logger=none", f"data.root={root}",
                           f"paths.checkpoints={tmp_path / 'ck'}", "runtime.report_on_end=false"])
    t0 = time.perf_counter()
    with pytest.raises(DataError, match=png.name):
        run_job(cfg, JobInfo(output_dir=tmp_path / "out", base_dir=tmp_path))
    assert time.perf_counter() - t0 < 60
    assert not (tmp_path / "ck").exists()  # the models stage never started
    status = json.loads((tmp_path / "out" / "pcrcg_status.json").read_text())
    assert status["status"] == "failed" and png.name in status["error"]


# --------------------------------------------------------------------------- data preparation


def test_same_seed_same_bytes_two_tiny_builds(tiny_root, tmp_path):
    """A second ``prepare profile=tiny`` into another root: every file identical (the manifest after
    its wall-clock fields)."""
    from pcrcg.data.materialise import prepare_dataset

    other = prepare_dataset(tiny_data_cfg(tmp_path / "again"), seed=0, log=lambda m: None)
    skip = {".pcrcg-inputs-ok.json"}  # written by runs' input checks, not by prepare
    files = sorted(p.relative_to(tiny_root) for p in tiny_root.rglob("*") if p.is_file() and p.name not in skip)
    assert files == sorted(p.relative_to(other) for p in other.rglob("*") if p.is_file() and p.name not in skip)
    assert len(files) > 500
    differ = [str(f) for f in files if f.name != "manifest.json"
              and (tiny_root / f).read_bytes() != (other / f).read_bytes()]
    assert differ == []

    def manifest(root):
        m = json.loads((root / "manifest.json").read_text())
        m.pop("created")
        m["stats"].pop("seconds")
        return m

    assert manifest(tiny_root) == manifest(other)


def test_stale_temp_folders_are_removed_without_a_rebuild(tiny_root, tmp_path):
    from pcrcg.data.materialise import prepare_dataset

    root = tmp_path / "d"
    shutil.copytree(tiny_root, root)
    dead = _dead_pid()
    (tmp_path / f"d.tmp-{dead}" / "fragments").mkdir(parents=True)
    (tmp_path / f"d.old-{dead}").mkdir()
    live = tmp_path / f"d.tmp-{os.getppid()}"
    live.mkdir()
    logs = []
    assert prepare_dataset(tiny_data_cfg(root), seed=0, log=logs.append) == root
    assert any("up to date" in m for m in logs)
    assert not (tmp_path / f"d.tmp-{dead}").exists() and not (tmp_path / f"d.old-{dead}").exists()
    assert live.exists()  # a running process's folder is left alone


_POOL = """
import os, sys, time
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pcrcg.data import materialise
init = materialise._die_with_parent if sys.argv[1] == "fixed" else materialise.set_parent
with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn"), initializer=init, initargs=(os.getpid(),)) as pool:
    list(pool.map(time.sleep, [120, 120]))  # a long step that never looks at its parent (fusion, say)
"""


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[-1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[-1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_pool_workers_die_with_their_parent(tmp_path):
    """The pool of ``prepare`` (spawned workers, :func:`materialise._die_with_parent` as initializer):
    SIGKILL of the parent ends the workers at once, even in a step that does not check on it."""
    p = subprocess.Popen([sys.executable, "-c", _POOL, "fixed"], cwd=REPO)
    try:
        _wait_for(lambda: len(_children(p.pid)) >= 2, 120, "the pool workers", p)
        time.sleep(3.0)  # the workers import and run their initializer
        workers = _children(p.pid)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(30)
        _wait_for(lambda: not any(_alive(w) for w in workers), 10, "the workers to end")
    finally:
        p.kill()
        for w in _children(p.pid):
            os.kill(w, signal.SIGKILL)


# --------------------------------------------------------------------------- one line, exit 2


def _entry(module: str, args: list[str], cwd: Path, monkeypatch, capsys) -> tuple[int, str]:
    """Run an entry point in this process as ``python -m <module> <args>``; (exit code, stderr)."""
    import importlib
    import runpy

    monkeypatch.chdir(cwd)
    target = "pcrcg.report.__main__" if module == "pcrcg.report" else module
    if module == "pcrcg.pretrain2d":
        target = "pcrcg.pretrain2d.__main__"
    monkeypatch.setattr(sys, "argv", [module, "--config-path", str(REPO / "conf"), *args,
                                      f"hydra.run.dir={cwd / 'hydra'}"])
    capsys.readouterr()
    code = 0
    try:
        if module == "pcrcg.run":
            importlib.import_module("pcrcg.run").main()
        else:
            runpy.run_module(target, run_name="__main__")
    except SystemExit as e:
        code = int(e.code or 0)
    return code, capsys.readouterr().err


@pytest.mark.parametrize("module,args,text", [
    ("pcrcg.run", ["trainer.optim.lr=abc"], "trainer.optim.lr='abc'"),
    ("pcrcg.run", ["eval.n_points=[0]"], "eval.n_points=0"),
    ("pcrcg.run", ["profile.train.max_epochs=-1"], "profile.train.max_epochs=-1"),
    ("pcrcg.run", ["trainer.optim.name=rmsprop"], "trainer.optim.name='rmsprop'"),
    ("pcrcg.run", ["profile=tiny", "profile.train.max_steps=0"], "profile.train.max_steps=0"),
    ("pcrcg.run", ["+experiment=window_size", "hydra.sweeper.params.window_size=3,7"], "quote them"),
    ("pcrcg.run", ["no_such_key=1"], "To append to your config use +no_such_key=1"),
    ("pcrcg.run", ["model.voxel_size=[1,2"], "model.voxel_size='[1,2'"),
    ("pcrcg.prepare", ["profile=tiny", "profile.synth.width=abc"], "profile.synth.width='abc'"),
    ("pcrcg.prepare", ["profile=tiny", "seed=-1"], "seed=-1"),
    ("pcrcg.evaluate", ["profile=tiny", "mode=score", "benchmark_dir=/nowhere", "estimate_dir=/nowhere"], "/nowhere"),
    ("pcrcg.evaluate", ["profile=tiny", "mode=pair", "method=fpfh", "source=/nowhere.ply", "target=/x.ply"], "nowhere.ply"),
    ("pcrcg.prepare", ["profile=tiny", "force=abc"], "force='abc'"),
    ("pcrcg.prepare", ["data=nope"], "data/nope"),
    ("pcrcg.prepare", ["profile=tiny", "nosuch=1"], "nosuch"),
    ("pcrcg.prepare", ["profile=tiny", "data.root=[1,2"], "data.root='[1,2'"),
    ("pcrcg.report", ["tables=[nope]"], "nope"),
    ("pcrcg.report", ["paper_csv=nowhere.csv"], "nowhere.csv: the paper's numbers file (paper_csv) does not exist"),
    ("pcrcg.report", ["data.root=nowhere"], "data.root"),
    ("pcrcg.report", ["profile=nope"], "profile/nope"),
    ("pcrcg.report", ["stats.n_boot=abc"], "stats.n_boot='abc'"),
    ("pcrcg.report", ["stats.level=high"], "stats.level='high'"),
    ("pcrcg.pretrain2d", ["profile=tiny", "train.lr=abc"], "train.lr"),
])
def test_bad_values_are_one_line_and_exit_2(tmp_path, monkeypatch, capsys, module, args, text):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/mlflow.db")
    rc, err = _entry(module, [*args, "logger=none"] if module == "pcrcg.run" else args, tmp_path, monkeypatch, capsys)
    assert rc == 2, err[-2000:]
    assert len(err.strip().splitlines()) == 1 and text in err and "Traceback" not in err, err
    assert not (tmp_path / "mlflow.db").exists()
    assert not list((tmp_path / "data").glob("*")) and not (tmp_path / "reports").exists()  # refused before work
