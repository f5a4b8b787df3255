"""Materialise a data set into ``data.root``: generated (synthmatch), real frames (redkitchen) or
the real 3DMatch release (threedmatch).

Writes happen in ``<root>.tmp-<pid>`` which is renamed into place only when complete, with a
``manifest.json`` holding the parameters' hash and the statistics; an interrupted run never leaves
a data set that looks finished. A finished data set with the same parameters is reused; one of the
same source with different parameters is replaced (only after the new one is complete) when the caller
asks for that (``python -m pcrcg.prepare``, whose job it is), and refused before any work starts when it
does not (a run: ``python -m pcrcg.run profile=paper data.root=data/synthmatch-cpu`` would otherwise spend
hours generating a paper-sized set and then delete the cpu one; the one-line error names the parameters
that differ and the command that replaces it). Nothing else is ever replaced: a ``data.root`` that holds
files and no manifest (a user's folder), or a data set of another source (the real 3DMatch scene under a
generated config), is refused before any work starts.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from pcrcg.data.build import SceneResult, build_scene, check_frames
from pcrcg.data.fusion import FusionConfig
from pcrcg.data.layout import BENCHMARKS, Layout, frame_ids, frame_paths, pinhole, write_matrix, write_pairs, write_split
from pcrcg.data.pairs import PairConfig
from pcrcg.data.synth.render import SensorModel
from pcrcg.data.synthmatch import SynthConfig, assign_splits, generate_scene, scene_name, set_parent
from pcrcg.errors import ConfigError, DataError

GENERATOR_VERSION = 7  # conf/data/common/version.yaml holds the same number (data.version); bump both
SOURCES = ("synthmatch", "redkitchen", "threedmatch")


# settings that must be > 0 (every other number of these dataclasses must be >= 0), and fractions
_POSITIVE = {"tsdf_voxel", "trunc_voxels", "depth_max", "overlap_radius", "fragment_seconds", "max_depth"}
_AT_MOST_ONE = {"min_overlap", "lo_match_max", "edge_drop", "dropout", "dark_drop", "grazing_cos", "grazing_soft"}


def _dc(cls, cfg: Mapping[str, Any] | None, setting: str):
    """Build dataclass ``cls`` from a mapping, naming the setting on unknown keys, on a value of the
    wrong type (``width=abc``) and on a number out of range (negative; 0 where it must be > 0)."""
    cfg = dict(cfg or {})
    names = {f.name: f for f in fields(cls)}
    unknown = sorted(set(cfg) - set(names))
    if unknown:
        raise ConfigError(f"{setting}.{unknown[0]}", cfg[unknown[0]], f"keys {sorted(names)}")
    for key, value in cfg.items():
        t = names[key].type
        kind = t.__name__ if isinstance(t, type) else str(t)
        where = f"{setting}.{key}"
        if kind == "bool":
            if not isinstance(value, bool):
                raise ConfigError(where, value, "true or false")
            continue
        if kind == "tuple[float, float]":  # a range [lo, hi] of fractions
            ok = (isinstance(value, (list, tuple)) and len(value) == 2
                  and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))
            if not (ok and 0 <= value[0] <= value[1] <= 1):
                raise ConfigError(where, value, "[lo, hi] with 0 <= lo <= hi <= 1")
            cfg[key] = (float(value[0]), float(value[1]))
            continue
        if kind == "int" and (isinstance(value, bool) or not isinstance(value, int)):
            raise ConfigError(where, value, "an integer")
        if kind == "float" and (isinstance(value, bool) or not isinstance(value, (int, float))
                                or not np.isfinite(value)):
            raise ConfigError(where, value, "a number")
        if kind in ("int", "float"):
            if key in _POSITIVE and not value > 0:
                raise ConfigError(where, value, "a number > 0")
            if value < 0:
                raise ConfigError(where, value, "a number >= 0")
            if key in _AT_MOST_ONE and value > 1:
                raise ConfigError(where, value, "a fraction in [0, 1]")
    return cls(**cfg)


def params_hash(params: Mapping[str, Any]) -> str:
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def read_manifest(root: Path) -> dict | None:
    try:
        return json.loads((root / "manifest.json").read_text())
    except (OSError, ValueError):
        return None


def prepare_dataset(data_cfg: Mapping[str, Any], seed: int = 0, force: bool = False, log: Callable[[str], None] = print,
                    replace: bool = True) -> Path:
    """Materialise the data set described by ``data_cfg`` (the ``data`` config node); returns its root.
    ``replace=False``: a finished data set of the same source made with other parameters is refused (a
    :class:`ConfigError` naming ``data.root`` and the parameters that differ) instead of replaced."""
    name = data_cfg.get("name")
    if name not in SOURCES:
        raise ConfigError("data.name", name, f"one of {SOURCES}")
    if "version" in data_cfg and str(data_cfg["version"]) != str(GENERATOR_VERSION):
        raise ConfigError("data.version", data_cfg["version"],
                          f"{GENERATOR_VERSION} (the data code in this checkout; the key is part of every run's "
                          "config hash so that runs on older data sets are not taken for finished ones)")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", seed, "an integer >= 0")
    workers = data_cfg.get("workers", 1)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError("data.workers", workers, "an integer >= 1 (processes generating scenes)")
    if _frames_only(data_cfg) and name != "synthmatch":
        raise ConfigError("data.frames_only", True, f"false for data.name={name} (only generated data render frames)")
    root = Path(str(data_cfg["root"]))
    _remove_stale_temps(root, log)
    params = {"source": name, "version": GENERATOR_VERSION, "seed": seed,
              **{k: v for k, v in data_cfg.items() if k not in ("root", "workers")}}
    h = params_hash(params)
    man = read_manifest(root)
    if man is not None and man.get("params_hash") == h and not force:
        log(f"[prepare] {root} is up to date (params {h}); reusing it")
        return root
    _check_replaceable(root, name, man)
    if man is not None and not replace:
        _refuse_other_params(root, man.get("params") or {}, params)
    if name == "synthmatch":
        job = lambda tmp: _prepare_synthmatch(tmp, data_cfg, seed, log)  # noqa: E731
    elif name == "redkitchen":
        _check_redkitchen_source(data_cfg)
        job = lambda tmp: _prepare_redkitchen(tmp, data_cfg, log)  # noqa: E731
    else:
        from pcrcg.data.release import prepare_release, source_from

        source_from(data_cfg)  # the release's folders, checked before anything is written
        job = lambda tmp: prepare_release(tmp, data_cfg, log)  # noqa: E731
    _atomic_build(root, h, params, job, log)
    return root


def _check_replaceable(root: Path, name: str, manifest: dict | None) -> None:
    """Refuse (one line naming ``data.root``) to build into a ``root`` whose contents this build would
    replace without having written them: a file, a non-empty folder with no ``manifest.json``, or a data
    set of another source than ``name`` (its manifest's ``params.name``)."""
    if not (root.exists() or root.is_symlink()):
        return
    if not root.is_dir():
        raise ConfigError("data.root", str(root), "a folder (this path is a file; nothing was changed)")
    if manifest is None:
        if any(root.iterdir()):
            raise ConfigError("data.root", str(root),
                              "a new or empty folder, or a data set this project wrote (this folder holds files "
                              "and no manifest.json, so it is not replaced; nothing was changed)")
        return
    held = (manifest.get("params") or {}).get("name")
    if held != name:
        raise ConfigError("data.root", str(root),
                          f"a folder for a {name} data set: it holds a {held} data set (its manifest.json), which "
                          f"a {name} config does not replace; choose another data.root, or data={held} to use it "
                          "(nothing was changed)")


def _flat(params: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in params.items():
        if isinstance(v, Mapping):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def param_differences(held: Mapping[str, Any], wanted: Mapping[str, Any], limit: int = 4) -> str:
    """The parameters that differ between a data set's manifest ``held`` and the config's ``wanted``, as
    ``key: held -> wanted`` (dotted keys, sorted; at most ``limit``, then how many more)."""
    a, b = _flat(held), _flat(wanted)
    keys = sorted(k for k in set(a) | set(b) if json.dumps(a.get(k), default=str) != json.dumps(b.get(k), default=str))
    shown = [f"{k}: {a.get(k, '(none)')} -> {b.get(k, '(none)')}" for k in keys[:limit]]
    if len(keys) > limit:
        shown.append(f"{len(keys) - limit} more")
    return ", ".join(shown) or "the parameters' hash"


def _refuse_other_params(root: Path, held: Mapping[str, Any], wanted: Mapping[str, Any]) -> None:
    """One line naming ``data.root``: it holds a finished data set made with other parameters, which only
    ``python -m pcrcg.prepare`` replaces."""
    raise ConfigError("data.root", str(root),
                      f"a new folder or a data set of this config; it holds one made with other parameters "
                      f"({param_differences(held, wanted, limit=3)}) that a run does not replace: choose another "
                      f"data.root, or replace it with python -m pcrcg.prepare (nothing was changed)")


def _remove_stale_temps(root: Path, log) -> None:
    """Remove ``<root>.tmp-<pid>`` / ``<root>.old-<pid>`` folders whose process is gone (a killed
    ``prepare``), on every call: also when the data set is up to date and nothing is rebuilt."""
    if not root.parent.is_dir():
        return
    for pattern in (root.name + ".tmp-*", root.name + ".old-*"):
        for stale in root.parent.glob(pattern):
            pid = stale.name.rsplit("-", 1)[-1]
            if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(pid):
                shutil.rmtree(stale, ignore_errors=True)
                log(f"[prepare] removed {stale} (left by process {pid}, which is gone)")


def _die_with_parent(parent: int) -> None:
    """Pool initializer: the worker gets SIGKILL when the process that started it dies (Linux
    ``PR_SET_PDEATHSIG``), so that killing ``prepare`` does not leave its workers running; elsewhere
    the generator's own check between frames (:func:`pcrcg.data.synthmatch.set_parent`) remains."""
    set_parent(parent)
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):  # pragma: no cover - no prctl
            pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _atomic_build(root: Path, h: str, params: dict, job: Callable[[Path], dict], log) -> None:
    root.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(root, log)
    tmp = root.parent / f"{root.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    t0 = time.time()
    try:
        stats = job(tmp)
        stats["seconds"] = round(time.time() - t0, 2)
        manifest = {"params_hash": h, "params": params, "stats": stats,
                    "created": time.strftime("%Y-%m-%dT%H:%M:%S")}
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2, default=str))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if root.exists() or root.is_symlink():
        old = root.parent / f"{root.name}.old-{os.getpid()}"
        os.replace(root, old)
    os.replace(tmp, root)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    log(f"[prepare] wrote {root} in {stats['seconds']} s")


def _pid_alive(pid: str) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


# --------------------------------------------------------------------------- statistics


def _stats(results: list[SceneResult], splits: dict[str, list[str]]) -> dict:
    split_of = {s: k for k, v in splits.items() for s in v}
    pairs_per_split = {k: 0 for k in ("train", "val")}
    bench = {b: 0 for b in BENCHMARKS}
    overlaps = []
    pts = []
    for r in results:
        pts += r.points_per_fragment
        overlaps += r.all_overlaps
        sp = split_of.get(r.scene, "test")
        if sp in pairs_per_split:
            pairs_per_split[sp] += len(r.pairs)
        for b, n in r.benchmark_counts.items():
            bench[b] += n
    hist, edges = np.histogram(overlaps, bins=[0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0001])
    return {
        "scenes": {k: len(v) for k, v in splits.items()},
        "fragments": int(sum(r.n_fragments for r in results)),
        "points_per_fragment": {"mean": float(np.mean(pts)) if pts else 0.0,
                                "min": int(min(pts)) if pts else 0, "max": int(max(pts)) if pts else 0},
        "pairs": {**pairs_per_split, **bench},
        "overlap_histogram": {f"{edges[k]:.2f}-{min(edges[k + 1], 1.0):.2f}": int(hist[k]) for k in range(len(hist))},
    }


def _write_pairs_files(layout: Layout, results: list[SceneResult], splits: dict[str, list[str]]) -> None:
    by_scene = {r.scene: r for r in results}
    for split in ("train", "val", "test"):
        write_split(layout.split_file(split), splits.get(split, []))
    for split in ("train", "val"):
        recs = [p for s in splits.get(split, []) for p in by_scene[s].pairs]
        write_pairs(layout.pairs_file(split), recs)


# --------------------------------------------------------------------------- synthmatch


def _prepare_synthmatch(tmp: Path, data_cfg: Mapping[str, Any], seed: int, log) -> dict:
    from tqdm import tqdm

    synth = _dc(SynthConfig, data_cfg.get("synth"), "data.synth")
    fusion = _dc(FusionConfig, data_cfg.get("fusion"), "data.fusion")
    pair_cfg = _dc(PairConfig, data_cfg.get("pairs"), "data.pairs")
    sensor = _dc(SensorModel, data_cfg.get("sensor"), "data.sensor")
    for key in ("width", "height", "fragments_per_scene", "frames_per_fragment", "n_scenes"):
        if getattr(synth, key) < 1:
            raise ConfigError(f"data.synth.{key}", getattr(synth, key), "a positive integer")
    if synth.fragments_per_scene < 2:
        raise ConfigError("data.synth.fragments_per_scene", synth.fragments_per_scene, ">= 2 (pairs need two fragments)")
    try:
        splits = assign_splits(synth.n_scenes, synth.n_val, synth.n_test, seed)
    except ValueError as exc:
        raise ConfigError("data.synth.n_scenes", synth.n_scenes, str(exc)) from None
    test = set(splits["test"])
    workers = max(1, int(data_cfg.get("workers", 1) or 1))
    frames_only = _frames_only(data_cfg)
    log(f"[prepare] synthmatch: {synth.n_scenes} scenes x {synth.fragments_per_scene} fragments x "
        f"{synth.frames_per_fragment} frames at {synth.width}x{synth.height}, {workers} worker(s)"
        f"{' (the frames only)' if frames_only else ''} -> {tmp}")
    args = [(str(tmp), k, seed, synth, sensor, fusion, pair_cfg, scene_name(k) in test, frames_only)
            for k in range(synth.n_scenes)]
    results: list[SceneResult] = []
    bar = tqdm(total=len(args), desc="scenes", unit="scene")
    if workers == 1:
        for a in args:
            results.append(generate_scene(*a))
            bar.update()
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                                 initializer=_die_with_parent, initargs=(os.getpid(),)) as pool:
            for r in pool.map(_generate_scene_star, args):
                results.append(r)
                bar.update()
    bar.close()
    layout = Layout(tmp)
    _write_pairs_files(layout, results, splits)
    stats = _stats(results, splits)
    n_frames = synth.n_scenes * synth.fragments_per_scene * synth.frames_per_fragment
    stats["frames"] = n_frames
    if not frames_only:
        _require_benchmarks(stats, "data.synth")
    return stats


def _frames_only(data_cfg: Mapping[str, Any]) -> bool:
    """``data.frames_only`` (absent: false): the scenes' RGB-D frames without fragments, pairs or benchmarks."""
    value = data_cfg.get("frames_only", False)
    if not isinstance(value, bool):
        raise ConfigError("data.frames_only", value, "true | false")
    return value


def _generate_scene_star(a):
    return generate_scene(*a)


def _require_benchmarks(stats: dict, setting: str) -> None:
    missing = [b for b in BENCHMARKS if stats["pairs"][b] == 0]
    if missing:
        raise ConfigError(setting, "(profile sizes)", f"sizes that yield test pairs in both benchmarks; "
                                                      f"none in {missing} (stats: {stats['pairs']})")


# --------------------------------------------------------------------------- redkitchen (real frames)


def _real_frame_ids(frames_dir: Path) -> list[int]:
    ids = frame_ids(frames_dir)
    if not ids:
        raise DataError(frames_dir, "no frame-XXXXXX.color.png or .color.jpg files (3DMatch RGB-D layout expected)")
    return ids


def _check_redkitchen_source(data_cfg) -> None:
    frames_dir = Path(str(data_cfg["frames_dir"]))
    if not frames_dir.is_dir():
        raise DataError(frames_dir, "frames folder (data.frames_dir) does not exist")
    if not (frames_dir / "camera-intrinsics.txt").is_file():
        raise DataError(frames_dir / "camera-intrinsics.txt", "intrinsics file is missing")
    if data_cfg.get("color_intrinsics") is not None:
        pinhole(data_cfg["color_intrinsics"], "data.color_intrinsics")
    _real_frame_ids(frames_dir)


def _prepare_redkitchen(tmp: Path, data_cfg, log) -> dict:
    frames_dir = Path(str(data_cfg["frames_dir"]))
    scene, seq = str(data_cfg["scene"]), str(data_cfg["seq"])
    fusion = _dc(FusionConfig, data_cfg.get("fusion"), "data.fusion")
    pair_cfg = _dc(PairConfig, data_cfg.get("pairs"), "data.pairs")
    fpf = int(data_cfg["frames_per_fragment"])
    ids = _real_frame_ids(frames_dir)
    layout = Layout(tmp)
    dst = layout.rgbd_dir(scene) / seq
    dst.mkdir(parents=True)
    shutil.copy2(frames_dir / "camera-intrinsics.txt", layout.intrinsics(scene))
    if data_cfg.get("color_intrinsics") is not None:  # colour not registered to depth (7-Scenes)
        write_matrix(layout.color_intrinsics(scene), pinhole(data_cfg["color_intrinsics"], "data.color_intrinsics"))
    for fid in ids:
        for src in frame_paths(frames_dir / f"frame-{fid:06d}"):
            if not src.is_file():
                raise DataError(src, "frame file is missing")
            shutil.copy2(src, dst / src.name)
    log(f"[prepare] redkitchen: checking {len(ids)} frames in {frames_dir}")
    check_frames(layout, scene, seq, ids)
    log(f"[prepare] redkitchen: fusing {len(ids)} frames, {fpf} per fragment")
    res = build_scene(layout, scene, seq, ids, fpf, fusion, pair_cfg, is_test=True)
    splits = {"train": [], "val": [], "test": [scene]}
    _write_pairs_files(layout, [res], splits)
    stats = _stats([res], splits)
    stats["frames"] = len(ids)
    return stats
