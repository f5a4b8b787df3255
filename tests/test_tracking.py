"""MLflow helpers: store URI resolution, config hash, params, git sha, runs, failures, parallel writers."""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import os
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from pcrcg.tracking.git import git_info
from pcrcg.pipeline import run_hash
from pcrcg.tracking.hashing import TRAIN_HASH_EXCLUDE, config_hash, flat_params, flatten
from pcrcg.tracking.store import artifact_root, resolve_tracking_uri, sqlite_path, ui_command


def test_uri_resolution_order(tmp_path):
    env = {"MLFLOW_TRACKING_URI": "http://tracking:5000"}
    assert resolve_tracking_uri("sqlite:////abs/x.db", tmp_path, env) == "sqlite:////abs/x.db"
    assert resolve_tracking_uri(None, tmp_path, env) == "http://tracking:5000"
    assert resolve_tracking_uri(None, tmp_path, {}) == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    # a relative SQLite path is made absolute against the base folder (jobs may run elsewhere)
    rel = resolve_tracking_uri(None, tmp_path, {"MLFLOW_TRACKING_URI": "sqlite:///stores/m.db"})
    assert rel == f"sqlite:///{tmp_path.resolve()}/stores/m.db"
    assert sqlite_path(rel) == tmp_path.resolve() / "stores" / "m.db"
    assert artifact_root(rel) == (tmp_path.resolve() / "stores" / "mlartifacts").as_uri()
    assert artifact_root("http://tracking:5000") is None
    assert ui_command(rel) == f"mlflow ui --backend-store-uri {rel}"


def _sha16(blob: bytes) -> str:
    return hashlib.sha256(blob).hexdigest()[:16]


def _cfg(**over):
    base = {
        "experiment_name": "window_size", "seed": 0, "window_size": 11, "method": "learned", "icp_init": "identity",
        "model": {"name": "predator", "dims": [64, 128]}, "eval": {"n_points": [5000, 250]},
        "logger": {"name": "mlflow", "tracking_uri": None}, "paths": {"data": "data"},
        "runtime": {"device": "auto"}, "stages": {"train": "a.b", "evaluate": "c.d"},
        "registration": {"n_points": [5000]},
    }
    cfg = OmegaConf.create(base)
    for k, v in over.items():
        OmegaConf.update(cfg, k, v)
    return cfg


def test_config_hash_ignores_bookkeeping_and_sees_everything_else():
    h = config_hash(_cfg())
    # the canonical JSON of what is left (sorted keys, no spaces), SHA-256, 16 hex chars
    kept = {"seed": 0, "window_size": 11, "method": "learned", "icp_init": "identity",
            "model": {"name": "predator", "dims": [64, 128]}, "eval": {"n_points": [5000, 250]},
            "stages": {"train": "a.b", "evaluate": "c.d"}, "registration": {"n_points": [5000]}}
    assert h == _sha16(json.dumps(kept, sort_keys=True, separators=(",", ":")).encode())
    for key, value in (("experiment_name", "other"), ("logger.tracking_uri", "sqlite:////x.db"),
                       ("paths.data", "/elsewhere"), ("runtime.device", "cuda")):
        assert config_hash(_cfg(**{key: value})) == h, key
    for key, value in (("seed", 1), ("window_size", 7), ("model.dims", [64, 256]), ("eval.n_points", [5000]),
                       ("stages.evaluate", "x.y")):
        assert config_hash(_cfg(**{key: value})) != h, key
    # the training hash also ignores evaluation-only settings (checkpoint reuse across them)
    t = config_hash(_cfg(), TRAIN_HASH_EXCLUDE)
    for key, value in (("method", "icp"), ("icp_init", "learned"), ("eval.n_points", [5000]), ("stages.evaluate", "x.y"),
                       ("registration.n_points", [250])):
        assert config_hash(_cfg(**{key: value}), TRAIN_HASH_EXCLUDE) == t, key
    assert config_hash(_cfg(window_size=7), TRAIN_HASH_EXCLUDE) != t


def test_hash_is_independent_of_key_order():
    a = OmegaConf.create({"a": 1, "b": {"x": 1, "y": 2}})
    b = OmegaConf.create({"b": {"y": 2, "x": 1}, "a": 1})
    assert config_hash(a) == config_hash(b)


def test_flatten_params():
    flat = flatten({"a": {"b": 1, "c": [1, 2], "d": None, "e": {}}, "f": "x"})
    assert flat == {"a.b": "1", "a.c": "[1, 2]", "a.d": "null", "a.e": "{}", "f": "x"}
    params = flat_params(_cfg())
    assert params["model.dims"] == "[64, 128]" and params["window_size"] == "11"


def test_git_info_reports_the_checkout():
    import subprocess

    sha, dirty = git_info()
    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent)
    if head.returncode != 0:  # not a git checkout (an unpacked copy)
        assert sha == "unknown"
        return
    assert sha == head.stdout.strip()
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout
    assert dirty == bool(status.strip())


def test_every_kind_of_run_gets_the_same_identity_tags(monkeypatch):
    """One function builds the tags a run (pcrcg.pipeline) and a 2D pretraining (pcrcg.pretrain2d)
    carry; the code version is among them."""
    import pcrcg.tracking.tracker as tracker
    from pcrcg.tracking.git import code_version

    tags = tracker.identity_tags("views", "0123abcd0123abcd", "cpu")
    sha, dirty = git_info()
    assert tags == {"experiment": "views", "config_hash": "0123abcd0123abcd", "git_sha": sha,
                    "git_dirty": str(dirty).lower(), "code_version": code_version(), "profile": "cpu",
                    "mlflow.source.git.commit": sha}
    monkeypatch.setattr(tracker, "git_info", lambda: ("e" * 40, True))
    assert tracker.identity_tags("x", "h", "tiny")["git_dirty"] == "true"
    assert tracker.identity_tags("x", "h", "tiny")["mlflow.source.git.commit"] == "e" * 40


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    from pcrcg.tracking.store import ensure_store

    uri = f"sqlite:///{tmp_path_factory.mktemp('store')}/mlflow.db"
    ensure_store(uri)
    return uri


def test_runs_finished_lookup_and_failure_record(store):
    from pcrcg.tracking.tracker import RunTracker

    tr = RunTracker(store, "unit")
    assert tr.find_finished("h1") is None
    failed = tr.start("window_size=3", {"config_hash": "h1"})
    tr.fail(failed, ValueError("boom"))
    assert tr.find_finished("h1") is None  # a failed run does not count as done
    run = tr.client.get_run(failed)
    assert run.info.status == "FAILED"
    assert run.data.tags["error"] == "boom" and run.data.tags["error_type"] == "ValueError"
    assert "error.txt" in [a.path for a in tr.client.list_artifacts(failed)]

    done = tr.start("window_size=3", {"config_hash": "h1"})
    tr.log_params(done, {f"p{i}": i for i in range(150)})  # more than one batch
    tr.log_metrics(done, {"3DLoMatch/rr_5000": 61.0})
    tr.log_history(done, {"train/loss": [1.0, 0.5, float("nan")], "val/loss": [(0, 2.0), (4, 1.0)]})
    tr.finish(done)
    found = tr.find_finished("h1")
    assert found is not None and found.run_id == done and found.run_name == "window_size=3"
    run = tr.client.get_run(done)
    assert len(run.data.params) == 150 and run.data.metrics["3DLoMatch/rr_5000"] == 61.0
    curve = tr.client.get_metric_history(done, "train/loss")
    assert [(m.step, m.value) for m in curve] == [(0, 1.0), (1, 0.5)]
    assert [m.step for m in tr.client.get_metric_history(done, "val/loss")] == [0, 4]

    not_run = tr.start("encoder2d=imagenet", {"config_hash": "h2"})
    from pcrcg.errors import ConfigError

    tr.fail(not_run, ConfigError("encoder2d.weights", None, "a local file"), not_run=True)
    assert tr.client.get_run(not_run).data.tags["not_run"] == "true"


def test_experiment_creation_is_idempotent_and_artifacts_sit_beside_the_db(store):
    from pcrcg.tracking.store import client, ensure_experiment

    c = client(store)
    a = ensure_experiment(c, "same", store)
    assert ensure_experiment(c, "same", store) == a
    loc = c.get_experiment(a).artifact_location
    assert loc == f"{artifact_root(store)}/same"
    c.delete_experiment(a)
    assert ensure_experiment(c, "same", store) == a  # restored, not duplicated


def _writer(uri: str, k: int, n: int) -> None:
    from pcrcg.tracking.tracker import RunTracker

    tr = RunTracker(uri, "parallel")
    for i in range(n):
        rid = tr.start(f"w{k}-{i}", {"config_hash": f"{k}-{i}"})
        tr.log_params(rid, {f"p{j}": j for j in range(40)})
        tr.log_metrics(rid, {f"m{j}": float(j) for j in range(25)})
        tr.finish(rid)


def test_parallel_writers_on_one_existing_store(tmp_path):
    """Two processes log into one SQLite store created beforehand: nothing is lost."""
    from pcrcg.tracking.tracker import RunTracker
    from pcrcg.tracking.store import client, ensure_experiment, ensure_store

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    ensure_experiment(client(uri), "parallel", uri)
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(uri, k, 3)) for k in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert all(p.exitcode == 0 for p in procs)
    tr = RunTracker(uri, "parallel")
    runs = tr.client.search_runs([tr.experiment_id], max_results=100)
    assert len(runs) == 6
    assert all(r.info.status == "FINISHED" and len(r.data.params) == 40 and len(r.data.metrics) == 25 for r in runs)
    assert Path(tmp_path / "mlflow.db").is_file()


def test_config_hash_follows_the_weights_file_contents(tmp_path):
    from pcrcg.tracking.hashing import config_hash

    w = tmp_path / "pri3d.pth"
    w.write_bytes(b"first weights")
    cfg = {"encoder2d": {"name": "pri3d", "weights": str(w)}, "seed": 0}
    h1 = config_hash(cfg)
    with_digest = {"encoder2d": {"name": "pri3d", "weights": str(w), "weights_digest": _sha16(b"first weights")},
                   "seed": 0}
    assert h1 == _sha16(json.dumps(with_digest, sort_keys=True, separators=(",", ":")).encode())
    w.write_bytes(b"retrained weights, same path")
    os.utime(w, ns=(1, 2))  # a new mtime even on coarse clocks
    h2 = config_hash(cfg)
    assert h2 != h1
    # no weights / missing file: the path alone (the preflight reports the missing file)
    for cfg in ({"encoder2d": {"name": "scratch", "weights": None}, "seed": 0},
                {"encoder2d": {"name": "pri3d", "weights": str(tmp_path / "missing.pth")}, "seed": 0}):
        assert config_hash(cfg) == _sha16(json.dumps(cfg, sort_keys=True, separators=(",", ":")).encode())


def test_weights_made_again_bit_for_bit_are_the_same_weights(tmp_path):
    """The 2D weights' digest covers the tensors, not the file's bytes: this project's weights file holds
    when and where it was made (``meta``), so the same pretraining run again on a fresh machine wrote other
    bytes and every finished run that loads it counted as another config. Other tensors: other weights."""
    import torch

    from pcrcg.tracking.hashing import config_hash, weights_digest

    state = {"enc.weight": torch.arange(6, dtype=torch.float32).reshape(2, 3), "bn.num_batches_tracked": torch.tensor(4)}

    def save(name, meta, sd=state):
        path = tmp_path / name
        torch.save({"format": "pcrcg-encoder2d", "version": 1, "arch": "resnet18", "state_dict": sd, "meta": meta}, path)
        return path

    first = save("a.pth", {"created": "2026-12-05 15:03:16", "seconds": 809.9})
    again = save("b.pth", {"created": "2026-12-05 15:47:23", "seconds": 416.5})
    assert first.read_bytes() != again.read_bytes()
    assert weights_digest(first) == weights_digest(again)
    cfg = lambda p: {"encoder2d": {"name": "pri3d", "weights": str(p)}, "seed": 0}  # noqa: E731
    assert config_hash(cfg(first)) != config_hash(cfg(again))  # the paths differ ...
    other = {**state, "enc.weight": state["enc.weight"] + 1e-6}
    assert weights_digest(save("c.pth", {"created": "x"}, other)) != weights_digest(first)
    # ... the same path made again with the same tensors: the same run identity
    h = config_hash(cfg(first))
    save("a.pth", {"created": "later"})
    os.utime(first, ns=(1, 2))
    assert config_hash(cfg(first)) == h
    # a plain state dict (an ImageNet file, say) by its tensors too; a file torch cannot read, by its bytes
    torch.save(state, tmp_path / "plain.pth")
    torch.save(dict(state), tmp_path / "plain2.pth")
    assert weights_digest(tmp_path / "plain.pth") == weights_digest(tmp_path / "plain2.pth")
    (tmp_path / "raw.bin").write_bytes(b"not torch")
    assert weights_digest(tmp_path / "raw.bin") == _sha16(b"not torch")


# --------------------------------------------------------------------------- run identity: config and code


def test_how_many_processes_and_threads_do_the_work_and_where_pyramids_are_kept_is_left_out_of_both_hashes():
    from pcrcg.config import load_run_config
    from pcrcg.tracking.hashing import HASH_EXCLUDE

    base = load_run_config(["profile=tiny"])
    how = load_run_config(["profile=tiny", "data.workers=1", "trainer.num_threads=2", "profile.train.num_threads=2",
                           "registration.ransac.threads=2", "profile.train.pyramid_cache=cache/pyramids"])
    a, b = flat_params(base), flat_params(how)
    assert {k for k in a if a[k] != b[k]} == {"data.workers", "trainer.num_threads", "profile.train.num_threads",
                                              "registration.ransac.threads", "trainer.cache_dir",
                                              "profile.train.pyramid_cache"}
    for exclude in (HASH_EXCLUDE, TRAIN_HASH_EXCLUDE):
        assert config_hash(how, exclude) == config_hash(base, exclude)
    # the loader processes draw the training augmentations: their number changes the model
    workers = load_run_config(["profile=tiny", "trainer.num_workers=2"])
    assert config_hash(workers, TRAIN_HASH_EXCLUDE) != config_hash(base, TRAIN_HASH_EXCLUDE)


def test_the_code_version_digests_the_code_that_computes_results(tmp_path):
    from pcrcg.tracking.git import code_version

    pkg = tmp_path / "pkg"
    for rel, text in (("models/net.py", "x = 1\n"), ("report/tables.py", "y = 1\n"), ("resources/notes.txt", "z")):
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    version = code_version.__wrapped__  # not the per-process memo: the files change below
    assert version(pkg) == _sha16(b"models/net.py 6\nx = 1\n")
    (pkg / "report" / "tables.py").write_text("y = 2\n")  # tables, figures, benchmarks: the same code version
    assert version(pkg) == _sha16(b"models/net.py 6\nx = 1\n")
    (pkg / "models" / "net.py").write_text("x = 2\n")
    assert version(pkg) == _sha16(b"models/net.py 6\nx = 2\n")


def _identity_job(tmp_path, monkeypatch, code: str, *overrides: str):
    """A classical run with the fake stages (tests/test_run_support.py) as if made by code version ``code``."""
    import pcrcg.pipeline as pipeline
    import pcrcg.tracking.tracker as tracker
    from pcrcg.config import load_run_config
    from test_run_support import FAKES

    monkeypatch.setattr(pipeline, "code_version", lambda: code)  # the skip rule's
    monkeypatch.setattr(tracker, "code_version", lambda: code)  # the run's tag (identity_tags)
    cfg = load_run_config(["profile=tiny", "method=fpfh", "experiment_name=identity", "runtime.report_on_end=false",
                           *FAKES, *overrides])
    n = len(list(tmp_path.glob("out-*")))
    return pipeline.run_job(cfg, pipeline.JobInfo(output_dir=tmp_path / f"out-{n}", base_dir=tmp_path,
                                                  overrides=list(overrides), multirun=True))


def test_the_skip_rule_follows_logger_identity(tmp_path, monkeypatch, capsys):
    from pcrcg.errors import ConfigError
    from test_run_support import tracked_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    first = _identity_job(tmp_path, monkeypatch, "A")
    assert first.status == "finished"
    assert _identity_job(tmp_path, monkeypatch, "A").status == "skipped"  # same config, same code
    capsys.readouterr()
    again = _identity_job(tmp_path, monkeypatch, "B")  # the default, config_and_code: other code runs again
    assert again.status == "finished" and again.config_hash == first.config_hash
    assert f"run {first.run_id} with config hash {first.config_hash} FINISHED with other code" in capsys.readouterr().out
    runs = {r.info.run_id: r.data.tags["code_version"] for r in tracked_runs(uri, "identity")}
    assert runs == {first.run_id: "A", again.run_id: "B"}
    # identity=config: a finished run of the same config counts, whatever code made it
    skipped = _identity_job(tmp_path, monkeypatch, "C", "logger.identity=config")
    assert (skipped.status, skipped.run_id) == ("skipped", again.run_id)
    with pytest.raises(ConfigError, match="logger.identity='code'"):
        _identity_job(tmp_path, monkeypatch, "C", "logger.identity=code")


def test_a_finished_job_that_runs_again_says_which_setting_changed(tmp_path, monkeypatch, capsys):
    """A relaunched job whose config hash changed under the same overrides (here: the 2D weights file was
    made again, with other bytes, as on a machine that lost checkpoints/) runs again and says why, naming
    the setting with both values; the digest is logged with the run's params."""
    from test_run_support import tracked_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    w = tmp_path / "pri3d.pth"
    w.write_bytes(b"weights made in the first sitting")
    first = _identity_job(tmp_path, monkeypatch, "A", f"encoder2d.weights={w}")
    assert first.status == "finished"
    w.write_bytes(b"weights made again on a fresh machine")
    capsys.readouterr()
    again = _identity_job(tmp_path, monkeypatch, "A", f"encoder2d.weights={w}")
    out = capsys.readouterr().out
    assert again.status == "finished" and again.config_hash != first.config_hash
    old, new = _sha16(b"weights made in the first sitting"), _sha16(b"weights made again on a fresh machine")
    assert (f"run {first.run_id} of the same job 'encoder2d.weights={w}' FINISHED with config hash "
            f"{first.config_hash}, this config is {again.config_hash}: running it; what differs: "
            f"encoder2d.weights_digest (here: {new}, there: {old})") in out
    params = {r.info.run_id: r.data.params.get("encoder2d.weights_digest") for r in tracked_runs(uri, "identity")}
    assert params == {first.run_id: old, again.run_id: new}
    # the same config again: skipped, no such line
    assert _identity_job(tmp_path, monkeypatch, "A", f"encoder2d.weights={w}").status == "skipped"
    assert "of the same job" not in capsys.readouterr().out


def test_the_checkpoint_cache_key_follows_logger_identity(tmp_path, monkeypatch):
    import json

    import pcrcg.models.train as train_module
    import pcrcg.pipeline as pipeline
    from pcrcg.config import load_run_config

    def fake_train(cfg, *, data_root, out_dir, logger, device):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "fake.ckpt").write_bytes(b"weights")
        return {"checkpoint": str(out_dir / "fake.ckpt")}

    monkeypatch.setattr(train_module, "train", fake_train)
    monkeypatch.setattr(train_module, "read_checkpoint", lambda path: None)

    def train(code: str, *overrides: str):
        monkeypatch.setattr(pipeline, "code_version", lambda: code)
        cfg = load_run_config(["profile=tiny", "logger=none", *overrides])
        ctx = pipeline.RunContext(cfg=cfg, job=pipeline.JobInfo(output_dir=tmp_path, base_dir=tmp_path),
                                  out_dir=tmp_path, device="cpu")
        out = pipeline.train_model(ctx)
        return out.checkpoint.parent, out.reused, run_hash(cfg, TRAIN_HASH_EXCLUDE)

    cache_a, reused, plain = train("A")
    assert not reused and cache_a.name != plain
    assert json.loads((cache_a / "source.json").read_text())["code_version"] == "A"
    assert train("A")[:2] == (cache_a, True)
    cache_b, reused, _ = train("B")  # config_and_code: a model of other code is another model
    assert not reused and cache_b != cache_a
    cache_c, reused, plain_c = train("C", "logger.identity=config")  # config: the training config alone
    assert not reused and cache_c.name == plain_c == plain
    assert train("D", "logger.identity=config")[:2] == (cache_c, True)


def test_a_geometry_only_run_leaves_the_color_settings_out_of_its_identity():
    """One geometry-only model and run per seed serve every table: the 2D encoder, matcher, window and views
    a table sets for its color rows do not make its geometry-only row another run. A color run, and a
    classical method that reads the matcher (sift_dlt), keep them."""
    from pcrcg.config import load_run_config
    from pcrcg.tracking.hashing import HASH_EXCLUDE

    def hashes(*overrides: str) -> tuple[str, str]:
        cfg = load_run_config(["profile=tiny", *overrides])
        return run_hash(cfg, HASH_EXCLUDE), run_hash(cfg, TRAIN_HASH_EXCLUDE)

    geometry = hashes("features=none")
    for table_settings in (["encoder2d=pri3d", "matcher2d=lightglue"], ["window_size=3", "views=3"],
                           ["projection=explicit"], ["profile.lifting.image_size=[60,80]"]):
        assert hashes("features=none", *table_settings) == geometry
    assert hashes("features=none", "seed=1") != geometry
    assert hashes("features=none", "model.voxel_size=0.07") != geometry
    color = hashes("features=deep", "projection=explicit")
    assert hashes("features=deep", "projection=explicit", "matcher2d=lightglue") != color
    assert hashes("features=deep", "projection=explicit", "window_size=3") != color
    dlt = load_run_config(["profile=tiny", "method=sift_dlt"])
    dlt_orb = load_run_config(["profile=tiny", "method=sift_dlt", "matcher2d=orb"])
    assert run_hash(dlt) != run_hash(dlt_orb)
    # the plain config hash (what the 2D pretraining and the benchmarks use) is unchanged by this rule
    cfg = load_run_config(["profile=tiny", "features=none"])
    assert config_hash(cfg) != run_hash(cfg)


def test_a_run_that_reads_no_seed_is_one_run_whatever_the_seed():
    """ICP / ColorICP from the identity draw nothing at random: seed=0,1,2 is one run (its hash leaves the
    seed out, its tag says so), while a learned model, ICP from a learned estimate and FPFH (RANSAC) keep it."""
    from pcrcg.config import load_run_config, seed_independent
    from pcrcg.pipeline import JobInfo, _tags
    from pcrcg.tracking.hashing import to_plain

    def h(*overrides: str) -> str:
        return run_hash(load_run_config(["profile=tiny", *overrides]))

    for method in ("icp", "color_icp"):
        assert h(f"method={method}", "seed=1") == h(f"method={method}", "seed=0")
        assert h(f"method={method}", "icp_init=learned", "seed=1") != h(f"method={method}", "icp_init=learned")
    for other in ("method=fpfh", "method=learned", "method=sift_dlt"):
        assert h(other, "seed=1") != h(other, "seed=0"), other
    assert seed_independent({"method": "icp"}) and not seed_independent({})
    assert not seed_independent({"method": "icp", "icp_init": "learned"})
    cfg = load_run_config(["profile=tiny", "method=icp"])
    job = JobInfo(Path("."), Path("."), overrides=["method=icp"])
    assert _tags(cfg, to_plain(cfg), "h", job)["seed_independent"] == "true"
    cfg = load_run_config(["profile=tiny", "method=fpfh"])
    assert "seed_independent" not in _tags(cfg, to_plain(cfg), "h", job)


def test_runs_of_stores_from_before_the_pyramid_folder_keep_their_hashes():
    """Until the pyramid folder existed every config had ``trainer.cache_dir: null`` and no
    ``profile.train.pyramid_cache``: such a config hashes as today's (the cpu profile keeps its pyramids in
    cache/pyramids), so the finished runs of older stores are still found."""
    from pcrcg.config import load_run_config
    from pcrcg.tracking.hashing import HASH_EXCLUDE, to_plain

    cfg = load_run_config(["profile=cpu"])
    assert cfg.trainer.cache_dir == "cache/pyramids"
    old = to_plain(cfg)
    del old["profile"]["train"]["pyramid_cache"]
    old["trainer"]["cache_dir"] = None
    new_keys = ("trainer.cache_dir", "profile.train.pyramid_cache")
    for exclude in (HASH_EXCLUDE, TRAIN_HASH_EXCLUDE):
        before = tuple(k for k in exclude if k not in new_keys)  # how the code before the folder hashed
        assert config_hash(cfg, exclude) == config_hash(old, before) == config_hash(old, exclude)
    assert "cache_dir" in to_plain(cfg)["trainer"]  # the hashed copy is changed, not the config


def test_runs_of_stores_from_before_the_schedule_settings_keep_their_hashes():
    """``trainer.optim.schedule`` / ``warmup_steps`` came after the store of record: a config at their old values
    (exponential, 0) hashes as the same config without them, in both hashes and in the run's identity; any other
    value is another run (and another training)."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import run_hash
    from pcrcg.tracking.hashing import HASH_EXCLUDE, to_plain

    cfg = load_run_config(["profile=cpu", "registration=inlier_ranking"])
    assert (cfg.trainer.optim.schedule, cfg.trainer.optim.warmup_steps) == ("exponential", 0)
    old = to_plain(cfg)
    del old["trainer"]["optim"]["schedule"], old["trainer"]["optim"]["warmup_steps"]
    for exclude in (HASH_EXCLUDE, TRAIN_HASH_EXCLUDE):
        assert config_hash(cfg, exclude) == config_hash(old, exclude)
        assert run_hash(cfg, exclude) == run_hash(old, exclude)
    for change in (["trainer.optim.schedule=cosine"], ["trainer.optim.warmup_steps=10"]):
        other = load_run_config(["profile=cpu", "registration=inlier_ranking", *change])
        for exclude in (HASH_EXCLUDE, TRAIN_HASH_EXCLUDE):
            assert run_hash(other, exclude) != run_hash(cfg, exclude)
    assert "schedule" in to_plain(cfg)["trainer"]["optim"]  # the hashed copy is changed, not the config


def test_runs_of_stores_from_before_the_window_style_keep_their_hashes():
    """``projection.window_style`` came after the store of record, whose explicit runs drew centred windows: a config at
    ``centred`` hashes as the same config without the key; ``official`` (the default since) is another run (and
    another training)."""
    from pcrcg.config import load_run_config
    from pcrcg.pipeline import run_hash
    from pcrcg.tracking.hashing import HASH_EXCLUDE, to_plain

    base = ["profile=cpu", "features=deep", "projection=explicit", "encoder2d=scratch"]
    cfg = load_run_config([*base, "projection.window_style=centred"])
    old = to_plain(cfg)
    del old["projection"]["window_style"]
    default = load_run_config(base)
    assert default.projection.window_style == "official"
    for exclude in (HASH_EXCLUDE, TRAIN_HASH_EXCLUDE):
        assert config_hash(cfg, exclude) == config_hash(old, exclude)
        assert run_hash(cfg, exclude) == run_hash(old, exclude)
        assert run_hash(default, exclude) != run_hash(cfg, exclude)
