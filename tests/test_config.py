"""Validation of the run config: every group, the top-level keys, sweeps, and the CLI."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from pcrcg.config import (
    CONF_DIR,
    check_overrides,
    check_sweep_params,
    group_options,
    load_run_config,
    preflight,
    validate_run_config,
)
from pcrcg.errors import ConfigError, DataError
from test_run_support import make_conf

EXPERIMENTS = tuple(group_options("experiment"))  # every experiment file (conf/experiment/*.yaml)


@pytest.fixture(scope="module")
def conf(tmp_path_factory) -> Path:
    return make_conf(tmp_path_factory.mktemp("cfg") / "conf")


def _error(conf: Path, overrides: list[str]) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_run_config(overrides, conf)
    return info.value


def test_defaults_compose_and_validate(conf):
    cfg = load_run_config([], conf)
    assert cfg.method == "learned" and cfg.views == 2 and cfg.window_size == 11
    assert cfg.profile.name == "cpu" and cfg.experiment_name == "default"
    assert list(cfg.eval.n_points) == [5000, 2500, 1000, 500, 250]
    assert cfg.eval.ransac_iterations == 50000 and cfg.eval.ransac_distance == pytest.approx(0.12)  # 2x the cpu profile's 6 cm voxel
    assert list(cfg.eval.benchmarks) == ["3DMatch", "3DLoMatch"]
    assert cfg.logger.name == "mlflow" and cfg.logger.tracking_uri is None


@pytest.mark.parametrize(
    "overrides, setting, allowed_words",
    [
        # top level
        (["views=5"], "views", "1, 2, 3"),
        (["views=0"], "views", "1, 2, 3"),
        (["window_size=0"], "window_size", "odd integer"),
        (["window_size=4"], "window_size", "odd integer"),
        (["method=superglue"], "method", "learned, fpfh, icp, color_icp, sift_dlt, sift_lifted"),
        (["seed=-1"], "seed", ">= 0"),
        (["icp_init=learned"], "icp_init", "icp, color_icp"),
        (["experiment_name=a/b"], "experiment_name", "without '/'"),
        (["eval.n_points=[5000,0]"], "eval.n_points", ">= 1"),
        (["eval.benchmarks=[3DMatch,KITTI]"], "eval.benchmarks", "3DMatch, 3DLoMatch"),
        (["eval.ransac_iterations=many"], "eval.ransac_iterations", "integer"),
        (["eval.fmr_threshold=5"], "eval.fmr_threshold", "(0, 1)"),
        (["stages.train=nowhere.train"], "stages.train", "importable"),
        # groups: an option that does not exist names the ones that do
        (["data=kitti"], "data", "synthmatch"),
        (["profile=huge"], "profile", "cpu, official, paper, tiny"),
        (["model=dgr"], "model", "predator"),
        (["encoder2d=resnet"], "encoder2d", "imagenet, pri3d, scratch"),
        (["features=normals"], "features", "deep, disk, none, rgb, sift"),
        (["projection=orthographic"], "projection", "explicit, implicit, none"),
        (["matcher2d=superglue"], "matcher2d", "sift"),
        (["trainer=tpu"], "trainer", "default"),
        (["logger=wandb"], "logger", "mlflow, none"),
        (["+experiment=table9"], "experiment", "main_results"),
        # values inside groups
        (["logger.name=wandb"], "logger.name", "mlflow, none"),
        (["logger.skip_finished=maybe"], "logger.skip_finished", "true or false"),
        (["profile.name=huge"], "profile.name", "cpu, official, paper, tiny"),
        (["features=deep", "projection=explicit", "features.name=normals"], "features.name", "rgb"),
        (["projection=explicit", "projection.name=orthographic"], "projection.name", "implicit"),
        (["data.name=kitti"], "data.name", "synthmatch"),
        (["encoder2d.name=resnet"], "encoder2d.name", "imagenet"),
        (["trainer=ddp", "trainer.strategy=dp"], "trainer.strategy", "ddp_spawn"),
        (["trainer.optim.name=lamb"], "trainer.optim.name", "adam"),
        (["trainer.optim.lr=0"], "trainer.optim.lr", "> 0"),
        (["trainer.optim.schedule=linear"], "trainer.optim.schedule", "exponential, cosine"),
        (["trainer.optim.warmup_steps=-1"], "trainer.optim.warmup_steps", ">= 0"),
        (["features=deep", "projection=explicit", "projection.window_style=square"], "projection.window_style",
         "centred, official"),
        (["features=deep", "projection=explicit", "projection.combine=max"], "projection.combine", "overwrite, mean"),
        (["features=deep", "projection=explicit", "projection.window_style=official", "window_size=1"], "window_size",
         "3 or more"),
        (["data.version=1"], "data.version", "the data code in this checkout"),
        # rules across groups
        (["features=deep", "projection=none"], "projection", "implicit or explicit"),
    ],
)
def test_bad_value_names_setting_and_allowed(conf, overrides, setting, allowed_words):
    err = _error(conf, overrides)
    assert err.setting == setting
    assert allowed_words in err.allowed
    assert setting in str(err) and "allowed" in str(err)


def test_group_rules_when_the_group_has_the_setting(conf):
    """Settings of other stages' groups are checked when their files define them."""
    cfg = load_run_config(["profile=tiny", "features=deep", "projection=explicit"], conf)
    data = OmegaConf.to_container(cfg, resolve=True)
    cases = {("encoder2d", "arch"): "resnet101", ("matcher2d", "ratio"): 1.5, ("features", "dim"): -1,
             ("projection", "depth_tolerance"): 0.0, ("trainer", "max_epochs"): 0}
    for (group, key), bad in cases.items():
        broken = OmegaConf.create(data)
        broken[group][key] = bad
        with pytest.raises(ConfigError) as info:
            validate_run_config(broken, None, [conf])
        assert info.value.setting == f"{group}.{key}"


def test_every_experiment_composes_and_each_sweep_value_is_valid(conf):
    for exp in EXPERIMENTS:
        cfg = load_run_config([f"+experiment={exp}", "profile=tiny"], conf)
        assert cfg.experiment_name == exp
        exp_yaml = OmegaConf.load(conf / "experiment" / f"{exp}.yaml")
        params = exp_yaml.hydra.sweeper.params
        assert len(params) >= 1
        check_sweep_params(params, [conf])
        # the sweep's last job composes and validates (composing all 24 jobs costs ~20 s)
        job = [f"{k}={str(v).split(',')[-1]}" for k, v in params.items()]
        load_run_config([f"+experiment={exp}", "profile=tiny", *job], conf)


def test_experiment_sweeps_match_the_paper_tables(conf):
    ws = OmegaConf.load(conf / "experiment" / "window_size.yaml").hydra.sweeper.params
    assert str(ws.window_size).split(",") == ["3", "7", "11", "17"]
    views = OmegaConf.load(conf / "experiment" / "views.yaml").hydra.sweeper.params
    assert str(views.views).split(",") == ["1", "2", "3"]
    bb = OmegaConf.load(conf / "experiment" / "backbone_2d.yaml").hydra.sweeper.params
    assert str(bb.encoder2d).split(",") == ["scratch", "imagenet", "pri3d"]
    proj = OmegaConf.load(conf / "experiment" / "projection.yaml").hydra.sweeper.params
    assert str(proj.features).split(",") == ["rgb", "sift", "deep", "disk"]
    assert str(proj.projection).split(",") == ["implicit", "explicit"]


def test_sweep_values_are_checked_one_by_one(conf):
    check_overrides(["views=1,2,3", "window_size=3,7,11,17", "projection=implicit,explicit"], [conf])
    with pytest.raises(ConfigError) as info:
        check_overrides(["window_size=3,8"], [conf])
    assert info.value.setting == "window_size" and info.value.value == 8
    with pytest.raises(ConfigError) as info:
        check_sweep_params({"views": "1,5"}, [conf])
    assert info.value.value == 5
    with pytest.raises(ConfigError) as info:
        check_overrides(["features=rgb,normals"], [conf])
    assert info.value.setting == "features" and info.value.value == "normals"
    # range sweeps are expanded too
    with pytest.raises(ConfigError):
        check_overrides(["views=range(1,5)"], [conf])


def test_ddp_preset_composes(conf):
    cfg = load_run_config(["trainer=ddp", "trainer.devices=4"], conf)
    assert cfg.trainer.accelerator == "gpu" and cfg.trainer.devices == 4
    assert cfg.trainer.strategy.startswith("ddp") and cfg.trainer.num_nodes == 1
    assert cfg.trainer.max_epochs == cfg.profile.train.max_epochs


def test_the_gpu_trainer_is_the_default_one_with_the_accelerator_changed(conf):
    default = load_run_config(["profile=paper"], conf).trainer
    gpu = load_run_config(["profile=paper", "trainer=gpu"], conf).trainer
    a, b = OmegaConf.to_container(default), OmegaConf.to_container(gpu)  # as written, interpolations unresolved
    assert {k for k in a.keys() | b.keys() if a.get(k) != b.get(k)} == {"accelerator"}
    assert (gpu.accelerator, gpu.num_workers) == ("gpu", 4)  # the paper profile's loader processes


@pytest.mark.parametrize("name", ["run", "prepare", "evaluate", "pretrain2d", "report"])
def test_every_entry_point_keeps_the_start_folder_and_writes_under_outputs(conf, name):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        hydra_cfg = compose(config_name=name, return_hydra_config=True).hydra
    assert hydra_cfg.job.chdir is False
    folder = OmegaConf.to_container(hydra_cfg.run)["dir"].replace("${hydra.job.config_name}", hydra_cfg.job.config_name)
    assert folder.startswith(f"outputs/{name}/") and folder.endswith("/${now:%Y-%m-%d_%H-%M-%S}_${pcrcg.pid:}")
    # resolved: the start time and this process's id, so that commands started in the same second do not share it
    resolved = OmegaConf.to_container(hydra_cfg.run, resolve=True)["dir"]
    assert re.fullmatch(rf"outputs/{name}/(\S+/)?\d{{4}}-\d\d-\d\d_\d\d-\d\d-\d\d_{os.getpid()}", resolved), resolved
    if name == "run":  # a sweep's folder too (its jobs are subfolders 0, 1, ...)
        sweep = OmegaConf.to_container(OmegaConf.create({"dir": hydra_cfg.sweep.dir}), resolve=True)["dir"]
        assert re.fullmatch(rf"multirun/\S+/[\d_-]+_{os.getpid()}", sweep), sweep


def test_group_options_lists_option_files(conf):
    assert group_options("projection", [conf]) == ["explicit", "implicit", "none"]
    assert "mlflow" in group_options("logger", [conf])


def test_preflight_pretrained_encoder_needs_weights(conf, tmp_path):
    cfg = load_run_config(["profile=tiny", "features=deep", "projection=explicit", "encoder2d=imagenet"], conf)
    with pytest.raises(ConfigError) as info:
        preflight(cfg)
    assert info.value.setting.startswith("encoder2d.")
    assert "nothing is downloaded" in info.value.allowed
    missing = tmp_path / "resnet18.pth"
    cfg.encoder2d.weights = str(missing)
    with pytest.raises(ConfigError) as info:
        preflight(cfg)
    assert info.value.setting == "encoder2d.weights" and info.value.allowed == "an existing local file"
    missing.write_bytes(b"x")  # there, but not a torch file: refused before any work, naming file and setting
    with pytest.raises(DataError, match=r"resnet18\.pth: encoder2d\.weights: refused by torch\.load\(weights_only=True\)"):
        preflight(cfg)
    torch.save({"conv1.weight": torch.zeros(1)}, missing)
    preflight(cfg)
    # without color the encoder is not used: no weights needed
    cfg2 = load_run_config(["profile=tiny", "encoder2d=imagenet"], conf)
    preflight(cfg2)


def test_cli_rejects_bad_values_before_any_work(conf, tmp_path, monkeypatch, capsys):
    from test_run_support import run_cli

    for args, word in ((["window_size=0"], "window_size"), (["projection=foo"], "projection"),
                       (["views=1,5", "-m"], "views")):
        rc = run_cli(["--config-path", str(conf), *args], tmp_path, monkeypatch)
        err = capsys.readouterr().err
        assert rc == 2
        assert f"invalid config value {word}=" in err and "allowed" in err
    assert not (tmp_path / "mlflow.db").exists()
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "multirun").exists()


@pytest.mark.parametrize("group", ["projection", "encoder2d"])
def test_the_options_of_a_group_extend_its_common_base_instead_of_copying_it(group):
    """Each option file of the group pulls ``common/base.yaml`` and writes only what differs: a key copied
    from the base with the same value would drift from it again. Every option composes with every base key."""
    import yaml

    folder = CONF_DIR / group
    base = yaml.safe_load((folder / "common" / "base.yaml").read_text())
    for path in sorted(folder.glob("*.yaml")):
        own = yaml.safe_load(path.read_text())
        assert own.get("defaults") == ["common/base@_here_", "_self_"], path.name
        copied = {k for k, v in own.items() if k in base and v == base[k] and k != "weights"}
        assert not copied, f"{path.name} repeats {sorted(copied)} of common/base.yaml"
        composed = load_run_config([f"{group}={path.stem}", "profile=tiny"], validate=False)[group]
        assert set(base) <= set(composed) and composed.get("name", composed.get("method")) == path.stem


def test_the_data_code_version_is_written_once_for_every_data_option():
    """``data.version`` lives in conf/data/common/version.yaml (beside GENERATOR_VERSION, which it must equal);
    every data option extends that file instead of writing its own number."""
    import yaml

    from pcrcg.data.materialise import GENERATOR_VERSION

    folder = CONF_DIR / "data"
    assert yaml.safe_load((folder / "common" / "version.yaml").read_text()) == {"version": GENERATOR_VERSION}
    for path in sorted(folder.glob("*.yaml")):
        own = yaml.safe_load(path.read_text())
        assert "version" not in own, f"{path.name} writes data.version itself"
        assert load_run_config([f"data={path.stem}", "profile=tiny"], validate=False).data.version == GENERATOR_VERSION


def test_a_pyramid_cache_folder_that_cannot_be_written_is_refused_at_the_start(conf, tmp_path):
    """trainer.cache_dir (the profile's pyramid_cache): a file in its place or above it is refused with the
    setting named, before any work; a folder that is not there yet is fine (made when the first pyramid is saved)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    for bad in (str(blocker), str(blocker / "pyramids")):
        err = _error(conf, ["profile=tiny", f"trainer.cache_dir={bad}"])
        assert err.setting == "trainer.cache_dir" and "is a file" in err.allowed
    err = _error(conf, ["profile=tiny", f"profile.train.pyramid_cache={blocker}"])  # the setting the user gave
    assert err.setting == "profile.train.pyramid_cache" and "is a file" in err.allowed
    cfg = load_run_config(["profile=tiny", f"trainer.cache_dir={tmp_path / 'not' / 'yet'}"], conf)
    assert cfg.trainer.cache_dir.endswith("not/yet") and not (tmp_path / "not").exists()


def test_config_check_imports_no_torch() -> None:
    """The config check runs before any long work: it takes the projection's rules from pcrcg.lifting.config
    (their one home) without the projection module, so checking a config never imports torch."""
    import subprocess
    import sys

    code = ("import sys, pcrcg.config, pcrcg.lifting.config; "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "from pcrcg.lifting import ColorLifter; assert 'torch' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
