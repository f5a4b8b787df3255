"""Config identity: the resolved config as plain data, its hash, and its flattened params.

Two jobs with the same hash compute the same thing, so a finished run with that hash
makes a new one unnecessary (with ``logger.identity=config_and_code``, the default, only when the code
version is also the same: :func:`pcrcg.tracking.git.code_version`). Keys that only say *where* or *how*
a run is recorded or computed (tracking, output paths, device, the MLflow experiment it is filed under,
processes and threads) are left out.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from omegaconf import DictConfig, OmegaConf

# keys that do not change what a run computes
# (profile.pretrain2d: the 2D pretraining's own sizes; a run reads only the weights file it is given;
# data.workers, trainer.num_threads (and the profile's value it follows), registration.ransac.threads: how many
# processes / CPU threads do the work; encoder2d.memo_mb, model.embedding_memo_mb: how much memory reuses 2D maps and
# GeoTransformer's embeddings; trainer.cache_dir (and
# the profile's value it follows): where the neighbour pyramids are kept between runs (the same pyramids, read
# instead of built; hashed as null, NEUTRAL below). trainer.num_workers
# stays, so that hashes match older stores', though since EpochSampler it changes no result: code before it drew
# the augmentations in the loader processes)
HASH_EXCLUDE: tuple[str, ...] = ("hydra", "logger", "experiment_name", "paths", "runtime", "profile.pretrain2d",
                                 "data.workers", "trainer.num_threads", "profile.train.num_threads",
                                 "registration.ransac.threads", "encoder2d.memo_mb", "model.embedding_memo_mb",
                                 "trainer.cache_dir",
                                 "profile.train.pyramid_cache")
# excluded keys that older configs had with one value for every run: hashed with that value instead of left out,
# so that the runs of older stores keep their hashes (trainer.cache_dir was null until it was excluded)
NEUTRAL: dict[str, Any] = {"trainer.cache_dir": None}
# settings added after runs were recorded, with the value that computes what the code before them computed: hashed
# only at another value (:func:`without_added`), so that the finished runs of older stores keep their hashes
ADDED: dict[str, Any] = {"trainer.optim.schedule": "exponential", "trainer.optim.warmup_steps": 0,
                         "projection.window_style": "centred"}
# ... and, in addition, keys that do not change what *training* computes (checkpoint cache key)
TRAIN_HASH_EXCLUDE: tuple[str, ...] = HASH_EXCLUDE + ("method", "icp_init", "eval", "registration", "stages.evaluate")
# settings that only a color run reads (the 2D encoder, the matcher, the projection and what it lifts): a learned
# geometry-only run leaves them out of its identity (pcrcg.pipeline.run_hash), so one geometry-only model (and
# run) per seed serves every table, whatever encoder2d, matcher2d, window or views the table sets for its color rows
COLOR_ONLY: tuple[str, ...] = ("encoder2d", "matcher2d", "projection", "features", "views", "window_size",
                               "profile.encoder2d", "profile.lifting")


def to_plain(cfg: DictConfig | Mapping[str, Any]) -> dict[str, Any]:
    """The resolved config as plain dicts/lists, without the ``hydra`` node."""
    if isinstance(cfg, DictConfig):
        data = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    else:
        data = dict(cfg)
    assert isinstance(data, dict)
    data.pop("hydra", None)
    return data


def _holder(data: Mapping[str, Any], key: str) -> tuple[Mapping[str, Any] | None, str]:
    """The mapping of nested ``data`` that holds the dotted ``key`` (``a.b.c``: ``data["a"]["b"]``, None where a
    level is missing) and the key's last part."""
    *parents, last = key.split(".")
    node: Any = data
    for p in parents:
        node = node.get(p) if isinstance(node, Mapping) else None
    return (node if isinstance(node, Mapping) else None), last


def without(data: Mapping[str, Any], exclude: Iterable[str]) -> dict[str, Any]:
    """A copy of the nested plain config ``data`` without the dotted keys (``a.b``) of ``exclude`` (those of
    :data:`NEUTRAL` that it has are set to their neutral value instead)."""
    out = json.loads(json.dumps(data, default=str))
    for key in exclude:
        node, last = _holder(out, key)
        if isinstance(node, dict) and last in node:
            if key in NEUTRAL:
                node[last] = NEUTRAL[key]
            else:
                del node[last]
    return out


def without_added(data: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of the nested plain config ``data`` without the settings of :data:`ADDED` that hold their value of
    before (a setting at any other value stays)."""
    at_before = []
    for key, before in ADDED.items():
        node, last = _holder(data, key)
        if node is not None and last in node and node[last] == before:
            at_before.append(key)
    return without(data, at_before)


_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 (16 hex chars) of a file's bytes, remembered per (path, size, mtime)."""
    st = os.stat(path)
    key = (str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        _DIGESTS[key] = h.hexdigest()[:16]
    return _DIGESTS[key]


_WEIGHTS_DIGESTS: dict[tuple[str, int, int], str] = {}


def weights_digest(path: str | os.PathLike) -> str:
    """What a weights file holds, as 16 hex chars, remembered per (path, size, mtime). A file that torch
    reads as tensors (``weights_only=True``: no code from it runs): the SHA-256 over its tensors (name,
    dtype, shape, bytes, in name order) and other values, of its ``state_dict`` where it has one (this
    project's format, whose ``meta`` holds when and where it was made: left out), so that weights made
    again bit for bit are the same weights. Any other file: its bytes (:func:`file_digest`)."""
    st = os.stat(path)
    key = (str(Path(path).resolve()), st.st_size, st.st_mtime_ns)
    if key not in _WEIGHTS_DIGESTS:
        import torch

        try:
            obj = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:  # not a torch file (or not one of tensors): its bytes
            obj = None
        if isinstance(obj, Mapping):
            content = obj.get("state_dict") if isinstance(obj.get("state_dict"), Mapping) else obj
            h = hashlib.sha256()
            _digest_tree(h, content, "")
            _WEIGHTS_DIGESTS[key] = h.hexdigest()[:16]
        else:
            _WEIGHTS_DIGESTS[key] = file_digest(path)
    return _WEIGHTS_DIGESTS[key]


def _digest_tree(h: "hashlib._Hash", node: Any, name: str) -> None:
    """Feeds ``node`` (nested mappings of tensors and plain values) into ``h`` in key order."""
    import torch

    if isinstance(node, Mapping):
        for k in sorted(node, key=str):
            _digest_tree(h, node[k], f"{name}/{k}")
    elif isinstance(node, torch.Tensor):
        t = node.detach().cpu().contiguous().reshape(-1)
        h.update(f"{name} {t.dtype} {tuple(node.shape)}\n".encode())
        h.update(t.view(torch.uint8).numpy().tobytes())
    else:
        h.update(f"{name} {node!r}\n".encode())


def with_weights_digest(data: dict[str, Any], by_bytes: bool = False) -> dict[str, Any]:
    """A run's identity includes what its 2D weights file holds, not only its path: retraining
    the weights into the same file makes the runs that load it new runs; making the same weights
    again does not (:func:`weights_digest`; ``by_bytes``: the file's bytes, :func:`file_digest`, as before)."""
    node = data.get("encoder2d")
    weights = node.get("weights") if isinstance(node, dict) else None
    if isinstance(weights, str) and weights and os.path.isfile(weights):
        node["weights_digest"] = file_digest(weights) if by_bytes else weights_digest(weights)
    return data


def config_hash(cfg: DictConfig | Mapping[str, Any], exclude: Iterable[str] = HASH_EXCLUDE) -> str:
    """16 hex chars of the SHA-256 of the canonical JSON of the resolved config minus ``exclude``, with its 2D
    weights' digest (:func:`with_weights_digest`)."""
    return data_hash(with_weights_digest(without_added(without(to_plain(cfg), exclude))))


def data_hash(data: Mapping[str, Any]) -> str:
    """16 hex chars of the SHA-256 of the canonical JSON of plain ``data``, hashed as it is."""
    blob = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Nested mapping -> ``{"a.b.c": "value"}``; lists become JSON text, None becomes ``"null"``."""
    out: dict[str, str] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            if value:
                out.update(flatten(value, name + "."))
            else:
                out[name] = "{}"
        elif isinstance(value, (list, tuple)):
            out[name] = json.dumps(list(value), default=str)
        elif value is None:
            out[name] = "null"
        else:
            out[name] = str(value)
    return out


def flat_params(cfg: DictConfig | Mapping[str, Any]) -> dict[str, str]:
    """The flattened resolved config (without ``hydra``): what a run logs as MLflow params."""
    return flatten(to_plain(cfg))
