"""Every input file of a run, checked before any long work (training, evaluation).

:func:`check_run_inputs` reads the scenes the run will read (``train``/``val`` when it trains, the
test scenes of the benchmarks it evaluates) and, in each, decodes every frame (color, depth: a
single-channel uint16 PNG of the color's size, pose: a finite rigid 4x4), the intrinsics, every
fragment a pair or a benchmark names, the pairs files and the benchmark files (``gt.log``,
``gt.info``). The first bad file is a :class:`~pcrcg.errors.DataError` naming it, in seconds, instead of
a traceback mid-training (train scenes) or after training (test scenes).

Frames are decoded on a thread pool (OpenCV releases the GIL). A passed check leaves a stamp
(``<root>/.pcrcg-inputs-ok.json``: a signature of the checked files' paths below the root, sizes and
modification times); while none of them changes, the next run only compares the stamp (a fraction of a
second). The stamp keeps the last :data:`STAMP_KEEP` signatures that passed, so that runs reading different
sets of files from one data set (a sweep's learned runs read train, val and test scenes, its FPFH or ICP
runs only the test scenes) do not undo each other's stamps, and paths are signed relative to the root, so
that the same data set reached through a link or moved elsewhere keeps its stamp.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from pcrcg.data.layout import (
    BENCHMARKS,
    Layout,
    frame_ids,
    frame_paths,
    read_cloud,
    read_color,
    read_depth,
    read_fragment_info,
    read_gt_info,
    read_gt_log,
    read_intrinsics,
    read_pairs,
    read_pose,
)
from pcrcg.errors import DataError

STAMP = ".pcrcg-inputs-ok.json"
_STAMP_VERSION = 2
STAMP_KEEP = 16  # signatures of passed checks a stamp keeps (the newest)


def run_splits(cfg: Any) -> tuple[list[str], list[str]]:
    """(pairs splits, benchmarks) a run reads: ``train``/``val`` when it trains, ``eval.benchmarks``."""
    from omegaconf import OmegaConf

    from pcrcg.config import needs_training

    splits = ["train", "val"] if needs_training(cfg) else []
    benches = [str(b) for b in (OmegaConf.select(cfg, "eval.benchmarks") or BENCHMARKS)]
    return splits, benches


def check_run_inputs(cfg: Any, root: str | os.PathLike, log: Callable[[str], None] = print) -> None:
    """Check the inputs of the run configured by ``cfg`` in the data set at ``root`` (see module doc)."""
    layout = Layout(root)
    if not (layout.root / "splits").is_dir() and not (layout.root / "fragments").is_dir():
        return  # not a data set in the layout (a stand-in stage's folder): nothing to check
    splits, benches = run_splits(cfg)
    check_inputs(layout, splits, benches, log=log)


def check_inputs(layout: Layout, splits: Sequence[str], benchmarks: Sequence[str],
                 log: Callable[[str], None] = print, workers: int | None = None) -> dict[str, int]:
    """Check the inputs of ``splits`` (pairs files) and ``benchmarks`` (test scenes); returns counts."""
    t0 = time.perf_counter()
    fragments: dict[str, set[int]] = {}
    texts: list[Path] = []
    for split in splits:
        f = layout.pairs_file(split)
        texts.append(f)
        for p in read_pairs(f):
            fragments.setdefault(p.scene, set()).update((p.i, p.j))
    for bench in benchmarks:
        d = layout.benchmark_dir(bench)
        if not d.is_dir():
            raise DataError(d, f"benchmark folder of {bench} is missing (eval.benchmarks names it)")
        for sd in sorted(p for p in d.iterdir() if p.is_dir()):
            for name in ("gt.log", "gt.info"):
                texts.append(sd / name)
            for r in read_gt_log(sd / "gt.log", sd.name):
                fragments.setdefault(sd.name, set()).update((r.i, r.j))
    files, frames, scenes_k = _input_files(layout, fragments)
    stamp_key = _signature([*texts, *files], layout.root)
    stamp = layout.root / STAMP
    if _stamp_ok(stamp, stamp_key):
        return {"files": len(files) + len(texts), "frames": len(frames), "cached": 1}
    for t in texts:
        if t.name == "gt.info":
            read_gt_info(t)
        elif t.name == "gt.log":
            read_gt_log(t)
    jobs: list[tuple[str, Any]] = [("frame", f) for f in frames]
    jobs += [("cloud", layout.fragment(s, i)) for s, ids in sorted(fragments.items()) for i in sorted(ids)]
    jobs += [("intrinsics", k) for k in scenes_k]
    n = workers or min(8, os.cpu_count() or 1)
    sizes: dict[tuple[str, str], tuple[int, int, Path]] = {}
    with ThreadPoolExecutor(n) as pool:
        for kind, result in pool.map(_check_one, jobs):
            if kind == "frame":
                key, shape, path = result
                first = sizes.setdefault(key, (*shape, path))
                if first[:2] != shape:
                    raise DataError(path, f"frame is {shape[1]}x{shape[0]} but {first[2].name} of the same "
                                          f"sequence is {first[1]}x{first[0]}")
    _write_stamp(stamp, stamp_key)
    log(f"[run] inputs checked: {len(frames)} frames, {sum(len(v) for v in fragments.values())} fragments, "
        f"{len(fragments)} scenes in {time.perf_counter() - t0:.1f} s")
    return {"files": len(files) + len(texts), "frames": len(frames), "cached": 0}


def _input_files(layout: Layout, fragments: Mapping[str, set[int]]):
    """(every file to sign, frame prefixes to decode, intrinsics files) of the fragments' scenes."""
    files: list[Path] = []
    frames: list[tuple[str, str, int, Path]] = []
    intrinsics: list[Path] = []
    listed: dict[Path, list[int]] = {}  # a sequence's frame ids, listed once for all its fragments
    for scene in sorted(fragments):
        seqs: dict[str, set[int]] = {}
        for i in sorted(fragments[scene]):
            cloud = layout.fragment(scene, i)
            if not cloud.is_file():
                raise DataError(cloud, f"fragment {i} of scene {scene} is missing (a pair or benchmark names it)")
            files.append(cloud)
            info = layout.fragment_info(scene, i)
            if not info.is_file():
                continue  # a fragment given without frames (e.g. a .pth release): no views to check
            files.append(info)
            fi = read_fragment_info(info)
            need = {fi.first_frame, fi.last_frame, (fi.first_frame + fi.last_frame) // 2}
            seqs.setdefault(fi.seq, set()).update(need)
            seq_dir = layout.rgbd_dir(scene) / fi.seq
            if seq_dir not in listed:
                listed[seq_dir] = frame_ids(seq_dir)
            seqs[fi.seq].update(k for k in listed[seq_dir] if fi.first_frame <= k <= fi.last_frame)
        if seqs:
            k = layout.intrinsics(scene)
            if not k.is_file():
                raise DataError(k, f"intrinsics of scene {scene} are missing")
            intrinsics.append(k)
            files.append(k)
        for seq, ids in sorted(seqs.items()):
            for fid in sorted(ids):
                prefix = layout.frame_prefix(scene, seq, fid)
                for p in frame_paths(prefix):
                    if not p.is_file():
                        raise DataError(p, f"frame file of scene {scene} is missing")
                    files.append(p)
                frames.append((scene, seq, fid, prefix))
    return files, frames, intrinsics


def _check_one(job: tuple[str, Any]) -> tuple[str, Any]:
    kind, what = job
    if kind == "frame":
        scene, seq, _, prefix = what
        cpath, dpath, ppath = frame_paths(prefix)
        color = read_color(cpath)
        depth = read_depth(dpath)
        if color.shape[:2] != depth.shape:
            raise DataError(dpath, f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                                   f"{color.shape[1]}x{color.shape[0]}")
        read_pose(ppath)
        return kind, ((scene, seq), depth.shape, cpath)
    if kind == "cloud":
        read_cloud(what)
        return kind, None
    read_intrinsics(what)
    return kind, None


def _signature(paths: Iterable[Path], root: Path) -> str:
    """sha256 of the files' paths (below ``root`` where they are), sizes and modification times."""
    h = hashlib.sha256(str(_STAMP_VERSION).encode())
    base = Path(os.path.abspath(root))
    for p in paths:
        st = p.stat()
        try:
            name = Path(os.path.abspath(p)).relative_to(base).as_posix()
        except ValueError:  # a file outside the data set (none today): its own path
            name = str(p)
        h.update(f"{name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _stamps(path: Path) -> dict[str, str]:
    """The signatures a stamp holds -> when each passed (empty when there is none or it is unreadable)."""
    try:
        got = json.loads(path.read_text())
        held = got.get("signatures")
        return {str(k): str(v) for k, v in held.items()} if isinstance(held, dict) else {}
    except (OSError, ValueError, AttributeError):
        return {}


def _stamp_ok(path: Path, key: str) -> bool:
    return key in _stamps(path)


def _write_stamp(path: Path, key: str) -> None:
    """Adds ``key`` to the stamp, keeping the newest :data:`STAMP_KEEP` signatures (written whole, then renamed:
    a run killed mid-write leaves the old stamp)."""
    held = {k: v for k, v in _stamps(path).items() if k != key}
    held[key] = time.strftime("%Y-%m-%dT%H:%M:%S")
    keep = dict(list(held.items())[-STAMP_KEEP:])
    try:
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
        tmp.write_text(json.dumps({"version": _STAMP_VERSION, "signatures": keep}, indent=0))
        os.replace(tmp, path)
    except OSError:  # a read-only data set: checked again next time
        pass
