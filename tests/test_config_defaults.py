"""One home per default (issue 17, item 5): the profiles extend conf/profile/common/base.yaml and write what
differs; the groups read a profile value as ``${profile.<key>}``, with no fallback that would copy it; the
options a group accepts are its files."""

from __future__ import annotations

import re

import pytest
import yaml
from omegaconf import OmegaConf

from pcrcg.config import CONF_DIR, group_options, load_run_config, profile_node
from pcrcg.errors import ConfigError

PROFILES = ("tiny", "cpu", "paper", "official")
BASE = CONF_DIR / "profile" / "common" / "base.yaml"


def _flat(node, prefix=""):
    out = {}
    for k, v in node.items():
        if isinstance(v, dict) and v:
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _conf_texts():
    return {p: p.read_text() for p in sorted(CONF_DIR.rglob("*.yaml"))}


def test_every_profile_extends_the_base_and_writes_only_what_differs():
    base = _flat(yaml.safe_load(BASE.read_text()))
    assert base["name"] == "???"  # each profile names itself
    assert group_options("profile") == sorted(PROFILES)  # common/base is no option
    for name in PROFILES:
        own = yaml.safe_load((CONF_DIR / "profile" / f"{name}.yaml").read_text())
        parent = "paper" if name == "official" else "common/base@_here_"
        assert own.pop("defaults") == [parent, "_self_"], name
        inherited = _flat(OmegaConf.to_container(profile_node("paper"))) if name == "official" else base
        copied = {k for k, v in _flat(own).items() if k in inherited and inherited[k] == v and k != "name"}
        assert not copied, f"{name}.yaml repeats {sorted(copied)} of what it extends"


def test_the_groups_read_profile_values_without_a_fallback_copy():
    """Every profile value a group reads has its default in common/base.yaml (a profile changes it there) and
    is read as ``${profile.<key>}``: no ``${oc.select:profile.<key>,<default>}`` keeps a second default. The
    only fallbacks left in conf/ are registration/default.yaml's reads of conf/run.yaml's ``eval.*`` and
    ``model.voxel_size``, which ``python -m pcrcg.evaluate`` composes without (the profile's value then)."""
    base = set(_flat(yaml.safe_load(BASE.read_text())))
    composed = {p: set(_flat(OmegaConf.to_container(profile_node(p)))) for p in PROFILES}
    assert base <= set.intersection(*composed.values())
    plain, fallbacks = set(), {}
    for path, text in _conf_texts().items():
        if path.parent.name == "profile" or path.parent.parent.name == "profile":
            continue
        plain |= set(re.findall(r"\$\{profile\.([\w.]+)\}", text))
        for key in re.findall(r"\$\{oc\.select:([\w.]+),", text):
            fallbacks.setdefault(path.relative_to(CONF_DIR).as_posix(), set()).add(key)
    sections = {k.rsplit(".", 1)[0] for k in base if "." in k}  # data.synth: ${profile.synth}
    assert plain and plain <= base | sections, sorted(plain - base - sections)
    assert fallbacks == {"registration/default.yaml": {"eval.n_points", "eval.ransac_iterations",
                                                       "eval.ransac_distance", "model.voxel_size"}}, fallbacks
    assert {"model.voxel_size", "train.max_epochs", "eval.n_points", "lifting.image_size", "train.optim.lr",
            "model.circle_points", "eval.max_pairs", "encoder2d.arch", "data_profile"} <= plain


@pytest.mark.parametrize("name", PROFILES)
def test_profile_node_is_what_hydra_composes(name):
    hydra = load_run_config([f"profile={name}"], validate=False).profile
    assert OmegaConf.to_container(profile_node(name), resolve=True) == OmegaConf.to_container(hydra, resolve=True)


def test_profile_values_reach_the_groups():
    cpu, paper = (load_run_config([f"profile={p}"]) for p in ("cpu", "paper"))
    assert cpu.model.voxel_size == 0.06 and paper.model.voxel_size == 0.025
    assert cpu.registration.ransac.distance == pytest.approx(0.12) and paper.registration.fpfh.voxel == 0.025
    assert (cpu.trainer.optim.name, cpu.trainer.optim.lr) == ("adam", 0.002)
    assert (paper.trainer.optim.name, paper.trainer.optim.lr) == ("sgd", 0.005)  # common/base.yaml's
    assert cpu.model.loss.max_points == 1024 and paper.model.loss.max_points == 256
    assert cpu.eval.max_pairs == 500 and paper.eval.max_pairs is None
    assert (cpu.trainer.num_workers, paper.trainer.num_workers, paper.trainer.cache_size) == (0, 4, 64)
    assert cpu.trainer.cache_size == 1024 and cpu.trainer.max_epochs == 12 and paper.trainer.max_epochs == 30
    assert (cpu.trainer.optim.lr_decay, paper.trainer.optim.lr_decay) == (0.75, 0.95)  # paper: common/base.yaml's
    assert list(cpu.encoder2d.image_size) == [120, 160] and list(paper.encoder2d.image_size) == [240, 320]
    assert list(cpu.projection.image_size) == list(paper.projection.image_size) == [120, 160]
    assert cpu.encoder2d.arch == "resnet18" and paper.encoder2d.arch == "resnet50"
    official = load_run_config(["profile=official"])
    assert (official.model.voxel_size, official.model.first_dim, official.trainer.max_epochs) == (0.025, 256, 150)
    assert official.data.root == paper.data.root == "data/synthmatch-paper" and cpu.data.root == "data/synthmatch-cpu"
    weights = load_run_config(["profile=official", "encoder2d=pri3d"]).encoder2d.weights
    assert weights == "checkpoints/pretrain2d/synthmatch-seed1-paper/pri3d_resnet50.pth"  # paper's pretraining
    tiny = load_run_config(["profile=tiny"])
    assert tiny.eval.ransac_iterations == tiny.registration.ransac.max_iterations == 10000
    assert tiny.data.synth.fragment_seconds == 1.667 and "sweep_deg" not in tiny.data.synth


@pytest.mark.parametrize(
    "overrides, setting, allowed",
    [
        (["profile.name=huge"], "profile.name", "one of cpu, official, paper, tiny"),
        (["logger.name=wandb"], "logger.name", "one of mlflow, none"),
        (["model.name=dgr"], "model.name", "one of cofinet, geotransformer, predator"),
    ],
)
def test_a_group_name_is_one_of_its_option_files(overrides, setting, allowed):
    with pytest.raises(ConfigError) as info:
        load_run_config(overrides)
    assert (info.value.setting, info.value.allowed) == (setting, allowed)
