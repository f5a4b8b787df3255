"""The real 3DMatch / 3DLoMatch release, whole or in part, into the layout (``data=threedmatch``).

Source (``data.source`` of ``conf/data/threedmatch.yaml``)::

    <benchmarks_dir>/{3DMatch,3DLoMatch}/<scene>/gt.log, gt.info[, gt_overlap.log]   official pairs
    <fragments_dir>/<scene>/cloud_bin_<k>.{ply,pth,npz}[, cloud_bin_<k>.info.txt]     fragments (optional)
    <rgbd_dir>/<scene>/camera-intrinsics.txt, <scene>/<seq>/frame-XXXXXX.*            RGB-D frames (optional)

A fragment ``k`` of a scene is *available* when

* its file exists (``.ply`` preferred over ``.pth`` over ``.npz``): read and written as ``.ply``
  (a ``.ply`` is copied as it is), or else
* all of its frames exist: fused the way 3DMatch made it (:func:`pcrcg.data.build.fuse_sequence`,
  ``data.fusion``), in the camera frame of its first frame. Its frames are those of the release's
  ``cloud_bin_<k>.info.txt`` when there is one, else frames ``F k .. F k + F - 1`` of
  ``data.source.seq`` (``F = data.frames_per_fragment``, 50 in 3DMatch).

Only the official pairs whose two fragments are available are kept (the log says how many were
dropped per benchmark); scenes without a kept pair are left out; nothing available at all is an
error. Where a fragment's frames are present, its ``.info.txt`` names them and the scene's RGB-D
folder is linked as ``<root>/rgbd/<scene>`` so that color models read the fragments' views.

Stages: :func:`read_official` (benchmark files) -> :func:`plan_release` (availability, kept pairs)
-> :func:`check_plan` (frames decoded, poses against gt.log: before any fusion) -> writing.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from pcrcg.data.build import check_frames, fuse_sequence
from pcrcg.data.fusion import FusionConfig
from pcrcg.data.layout import (
    BENCHMARKS,
    FragmentInfo,
    Layout,
    PairRecord,
    frame_paths,
    pinhole,
    read_cloud,
    read_fragment_info,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
    read_pose,
    write_fragment_info,
    write_gt_info,
    write_gt_log,
    write_gt_overlap,
    write_matrix,
    write_pairs,
    write_ply,
    write_split,
)
from pcrcg.errors import ConfigError, DataError
from pcrcg.geometry import invert

FRAGMENT_SUFFIXES = (".ply", ".pth", ".npz")  # in order of preference
POSE_TOLERANCE = 0.01  # max |inv(P_i) P_j - gt| entry where both fragments' first-frame poses are known

Log = Callable[[str], None]


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class ReleaseSource:
    """Where the release's parts are (``data.source``); ``None``: that part is absent."""

    benchmarks_dir: Path
    fragments_dir: Path | None
    rgbd_dir: Path | None
    seq: str = "seq-01"
    # scene-name prefix -> the colour camera's intrinsics (3, 3) where colour is not registered to
    # depth (data.source.color_intrinsics)
    color_intrinsics: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)

    def color_camera(self, scene: str) -> np.ndarray | None:
        """The colour camera's intrinsics (3, 3) for ``scene`` (the longest matching prefix), or None."""
        keys = sorted((k for k in self.color_intrinsics if scene.startswith(k)), key=len)
        return self.color_intrinsics[keys[-1]] if keys else None


@dataclass(frozen=True)
class OfficialScene:
    """One scene of an official benchmark: pairs (j into i), their 6x6 ``gt.info`` matrices and
    the overlaps of ``gt_overlap.log`` ({(i, j): ratio}, empty when the file is absent)."""

    scene: str
    pairs: tuple[PairRecord, ...]
    infos: tuple[np.ndarray, ...]
    overlaps: Mapping[tuple[int, int], float]


@dataclass(frozen=True)
class FragmentSource:
    """How fragment ``index`` of ``scene`` is made: read from ``file`` or fused from ``frames``
    (ids of ``seq``). ``info``: the release's ``.info.txt``; ``frames`` present: the views exist."""

    scene: str
    index: int
    file: Path | None
    info: Path | None
    seq: str
    frames: tuple[int, ...] | None  # ids, all present in the RGB-D folder; None: frames absent

    @property
    def fused(self) -> bool:
        return self.file is None


@dataclass
class ReleasePlan:
    """What will be built: kept pairs per benchmark and scene, dropped counts, fragments to make."""

    kept: dict[str, dict[str, OfficialScene]] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    official: dict[str, int] = field(default_factory=dict)
    fragments: dict[tuple[str, int], FragmentSource] = field(default_factory=dict)

    @property
    def scenes(self) -> list[str]:
        return sorted({s for by_scene in self.kept.values() for s in by_scene})


# --------------------------------------------------------------------------- config


def source_from(data_cfg: Mapping[str, Any]) -> ReleaseSource:
    """The checked ``data.source`` node: folders that are set must exist; fragments or frames needed."""
    src = dict(data_cfg.get("source") or {})
    known = {f.name for f in dataclasses.fields(ReleaseSource)}
    for key in sorted(set(src) - known):
        raise ConfigError(f"data.source.{key}", src[key], f"keys {sorted(known)}")
    if not src.get("benchmarks_dir"):
        raise ConfigError("data.source.benchmarks_dir", src.get("benchmarks_dir"),
                          "the folder of the official files (<dir>/{3DMatch,3DLoMatch}/<scene>/gt.log|gt.info)")
    bdir = Path(str(src["benchmarks_dir"]))
    for b in BENCHMARKS:
        if not (bdir / b).is_dir():
            raise DataError(bdir / b, "benchmark folder (data.source.benchmarks_dir) is missing")
    fdir = Path(str(src["fragments_dir"])) if src.get("fragments_dir") else None
    rgbd = Path(str(src["rgbd_dir"])) if src.get("rgbd_dir") else None
    if fdir is None and rgbd is None:
        raise ConfigError("data.source.fragments_dir", None, "the folder of the release's fragments "
                          "(<dir>/<scene>/cloud_bin_<i>.pth|.ply) and/or data.source.rgbd_dir (frames to fuse)")
    if fdir is not None and not fdir.is_dir():
        raise DataError(fdir, "fragments folder (data.source.fragments_dir) does not exist")
    if rgbd is not None and not rgbd.is_dir():
        raise DataError(rgbd, "RGB-D folder (data.source.rgbd_dir) does not exist")
    seq = str(src.get("seq") or "seq-01")
    color = {str(k): pinhole(v, f"data.source.color_intrinsics.{k}")
             for k, v in dict(src.get("color_intrinsics") or {}).items()}
    return ReleaseSource(bdir, fdir, rgbd, seq, color)


def fusion_from(data_cfg: Mapping[str, Any]) -> FusionConfig:
    """``data.fusion`` as a :class:`FusionConfig` (numbers coerced: Open3D refuses an int where it
    takes a float)."""
    cfg = dict(data_cfg.get("fusion") or {})
    out = {}
    for f in dataclasses.fields(FusionConfig):
        if f.name in cfg:
            cast = int if f.type in (int, "int") else float
            try:
                out[f.name] = cast(cfg.pop(f.name))
            except (TypeError, ValueError):
                raise ConfigError(f"data.fusion.{f.name}", data_cfg["fusion"][f.name], "a number") from None
    if cfg:
        key = sorted(cfg)[0]
        raise ConfigError(f"data.fusion.{key}", cfg[key], f"keys {[f.name for f in dataclasses.fields(FusionConfig)]}")
    fusion = FusionConfig(**out)
    if fusion.tsdf_voxel <= 0:
        raise ConfigError("data.fusion.tsdf_voxel", fusion.tsdf_voxel, "a voxel size > 0 (metres)")
    return fusion


def frames_per_fragment(data_cfg: Mapping[str, Any]) -> int:
    n = data_cfg.get("frames_per_fragment", 50)
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ConfigError("data.frames_per_fragment", n, "a positive integer (3DMatch: 50)")
    return n


# --------------------------------------------------------------------------- stages


def read_official(benchmarks_dir: Path) -> dict[str, dict[str, OfficialScene]]:
    """Every scene of both official benchmarks, checked: {benchmark: {scene: OfficialScene}}."""
    out: dict[str, dict[str, OfficialScene]] = {}
    for b in BENCHMARKS:
        out[b] = {}
        for sd in sorted(p for p in (benchmarks_dir / b).iterdir() if p.is_dir()):
            for f in ("gt.log", "gt.info"):
                if not (sd / f).is_file():
                    raise DataError(sd / f, "benchmark file is missing")
            recs = read_gt_log(sd / "gt.log", sd.name)
            infos = read_gt_info(sd / "gt.info")
            missing = [(r.i, r.j) for r in recs if (r.i, r.j) not in infos]
            if missing:
                raise DataError(sd / "gt.info", f"no information matrix for pair {missing[0][0]} {missing[0][1]} of gt.log")
            ov = read_gt_overlap(sd / "gt_overlap.log") if (sd / "gt_overlap.log").is_file() else {}
            recs = [PairRecord(sd.name, r.i, r.j, r.transform, ov.get((r.i, r.j), float("nan")), r.n_fragments)
                    for r in recs]
            out[b][sd.name] = OfficialScene(sd.name, tuple(recs), tuple(infos[(r.i, r.j)] for r in recs), ov)
    return out


def _frames_present(rgbd_scene: Path, seq: str, ids: range) -> bool:
    if not (rgbd_scene / "camera-intrinsics.txt").is_file():
        return False
    for fid in ids:
        if not all(p.is_file() for p in frame_paths(rgbd_scene / seq / f"frame-{fid:06d}")):
            return False
    return True


def locate_fragment(src: ReleaseSource, scene: str, k: int, fpf: int) -> FragmentSource | None:
    """How fragment ``k`` of ``scene`` can be made, or None when it cannot (no file, frames absent)."""
    file = info = None
    if src.fragments_dir is not None:
        d = src.fragments_dir / scene
        file = next((d / f"cloud_bin_{k}{x}" for x in FRAGMENT_SUFFIXES if (d / f"cloud_bin_{k}{x}").is_file()), None)
        if (d / f"cloud_bin_{k}.info.txt").is_file():
            info = d / f"cloud_bin_{k}.info.txt"
    seq, ids = src.seq, range(fpf * k, fpf * k + fpf)
    if info is not None:
        fi = read_fragment_info(info)
        seq, ids = fi.seq, range(fi.first_frame, fi.last_frame + 1)
    frames = None
    if src.rgbd_dir is not None and _frames_present(src.rgbd_dir / scene, seq, ids):
        frames = tuple(ids)
    if file is None and frames is None:
        return None
    return FragmentSource(scene, k, file, info, seq, frames)


def plan_release(src: ReleaseSource, official: Mapping[str, Mapping[str, OfficialScene]], fpf: int) -> ReleasePlan:
    """Keep the official pairs whose two fragments are available; a DataError when none is."""
    plan = ReleasePlan()
    located: dict[tuple[str, int], FragmentSource | None] = {}

    def available(scene: str, k: int) -> FragmentSource | None:
        if (scene, k) not in located:
            located[(scene, k)] = locate_fragment(src, scene, k, fpf)
        return located[(scene, k)]

    for b, by_scene in official.items():
        plan.kept[b], plan.dropped[b], plan.official[b] = {}, 0, 0
        for scene, off in by_scene.items():
            sel = [n for n, p in enumerate(off.pairs) if available(scene, p.i) and available(scene, p.j)]
            plan.official[b] += len(off.pairs)
            plan.dropped[b] += len(off.pairs) - len(sel)
            if sel:
                plan.kept[b][scene] = OfficialScene(scene, tuple(off.pairs[n] for n in sel),
                                                    tuple(off.infos[n] for n in sel), off.overlaps)
                for n in sel:
                    for k in (off.pairs[n].i, off.pairs[n].j):
                        plan.fragments[(scene, k)] = located[(scene, k)]
    if not plan.fragments:
        where = src.fragments_dir if src.fragments_dir is not None else src.rgbd_dir
        raise DataError(where, f"no official pair has both fragments available (as cloud_bin_<k>.ply|.pth|.npz in "
                               f"data.source.fragments_dir or as {fpf} frames each of <scene>/{src.seq} in "
                               "data.source.rgbd_dir): nothing to build")
    return plan


def check_plan(layout: Layout, plan: ReleasePlan) -> None:
    """Before any fusion: every frame a fragment uses is decoded and checked (:func:`check_frames`),
    and each kept pair's gt.log transform agrees with its fragments' first-frame poses."""
    first_pose: dict[tuple[str, int], np.ndarray] = {}
    for (scene, k), fs in sorted(plan.fragments.items()):
        if fs.frames is None:
            continue
        # a fused fragment's frames, a read fragment's views (first, last, middle)
        ids = fs.frames if fs.fused else sorted({fs.frames[0], fs.frames[-1], fs.frames[(len(fs.frames) - 1) // 2]})
        check_frames(layout, scene, fs.seq, ids)
        first_pose[(scene, k)] = read_pose(frame_paths(layout.frame_prefix(scene, fs.seq, fs.frames[0]))[2])
    for by_scene in plan.kept.values():
        for scene, off in by_scene.items():
            for p in off.pairs:
                Pi, Pj = first_pose.get((scene, p.i)), first_pose.get((scene, p.j))
                if Pi is None or Pj is None:
                    continue
                err = float(np.abs(invert(Pi) @ Pj - p.transform).max())
                if err > POSE_TOLERANCE:
                    fs = plan.fragments[(scene, p.j)]
                    raise DataError(layout.frame_prefix(scene, fs.seq, fs.frames[0]),
                                    f"pose disagrees with gt.log pair {p.i} {p.j} (max |dT| {err:.3f}): fragment "
                                    f"{p.j}'s frames are not {fs.frames[0]}..{fs.frames[-1]} (give its .info.txt)")


# --------------------------------------------------------------------------- writing


def _link_rgbd(src_scene: Path, layout: Layout, scene: str, K_color: np.ndarray | None = None) -> None:
    """The scene's frames in the layout: its intrinsics copied, its sequences linked (copied where
    the file system has no symlinks), and ``camera-intrinsics-color.txt`` when ``K_color`` is given
    (nothing is written into the release's own folder)."""
    dst = layout.rgbd_dir(scene)
    dst.mkdir(parents=True, exist_ok=True)
    for item in sorted(src_scene.iterdir()):
        if item.is_dir():
            try:
                os.symlink(item.resolve(), dst / item.name, target_is_directory=True)
            except OSError:  # no symlinks on this file system: copy
                shutil.copytree(item, dst / item.name)
        elif item.is_file():
            shutil.copy2(item, dst / item.name)
    if K_color is not None:
        write_matrix(layout.color_intrinsics(scene), K_color)


def _write_read_fragment(layout: Layout, fs: FragmentSource) -> int:
    """A fragment from its file (``.ply`` copied, others converted) and its ``.info.txt``; returns its size."""
    pts, cols = read_cloud(fs.file)
    dst = layout.fragment(fs.scene, fs.index)
    if fs.file.suffix.lower() == ".ply":
        shutil.copyfile(fs.file, dst)
    else:
        write_ply(dst, pts, cols)
    if fs.info is not None:
        shutil.copyfile(fs.info, layout.fragment_info(fs.scene, fs.index))
    elif fs.frames is not None:
        write_fragment_info(layout.fragment_info(fs.scene, fs.index),
                            FragmentInfo(fs.scene, fs.seq, fs.frames[0], fs.frames[-1]),
                            extra=f"# frames by 3DMatch's rule (fragment {fs.index} = {len(fs.frames)} frames from "
                                  f"{fs.frames[0]}); points from {fs.file.name}\n")
    return len(pts)


def _write_benchmarks(layout: Layout, plan: ReleasePlan) -> None:
    for b, by_scene in plan.kept.items():
        layout.benchmark_dir(b).mkdir(parents=True, exist_ok=True)
        for scene, off in by_scene.items():
            d = layout.benchmark_dir(b, scene)
            d.mkdir(parents=True, exist_ok=True)
            write_gt_log(d / "gt.log", off.pairs)
            write_gt_info(d / "gt.info", off.pairs, off.infos)
            have = {k for (s, k) in plan.fragments if s == scene}
            if off.overlaps:  # like the official file: every pair of the scene's fragments (those present)
                every = [PairRecord(scene, i, j, np.eye(4), ov) for (i, j), ov in sorted(off.overlaps.items())
                         if i in have and j in have]
            else:
                every = list(off.pairs)
            write_gt_overlap(d / "gt_overlap.log", every)


def prepare_release(tmp: Path, data_cfg: Mapping[str, Any], log: Log = print) -> dict:
    """Build the data set in ``tmp`` (see the module docstring); returns the manifest's statistics."""
    from tqdm import tqdm

    src = source_from(data_cfg)
    fusion = fusion_from(data_cfg)
    fpf = frames_per_fragment(data_cfg)
    official = read_official(src.benchmarks_dir)
    plan = plan_release(src, official, fpf)
    scenes = plan.scenes
    for b in BENCHMARKS:
        kept = sum(len(o.pairs) for o in plan.kept[b].values())
        log(f"[prepare] threedmatch: {b}: {kept} of {plan.official[b]} official pairs kept, {plan.dropped[b]} dropped "
            f"(a fragment neither in data.source.fragments_dir nor fusable from data.source.rgbd_dir)")
    n_left = len({s for by_scene in official.values() for s in by_scene}) - len(scenes)
    log(f"[prepare] threedmatch: {len(scenes)} test scene(s) {scenes}; {n_left} scene(s) without a kept pair left out")

    layout = Layout(tmp)
    for scene in scenes:
        layout.fragments_dir(scene).mkdir(parents=True, exist_ok=True)
        if src.rgbd_dir is not None and any(fs.frames for (s, _), fs in plan.fragments.items() if s == scene):
            _link_rgbd(src.rgbd_dir / scene, layout, scene, src.color_camera(scene))
    check_plan(layout, plan)

    read = [fs for fs in plan.fragments.values() if not fs.fused]
    fused = [fs for fs in plan.fragments.values() if fs.fused]
    points: dict[tuple[str, int], int] = {}
    for fs in sorted(read, key=lambda f: (f.scene, f.index)):
        points[(fs.scene, fs.index)] = _write_read_fragment(layout, fs)
    log(f"[prepare] threedmatch: {len(read)} fragment(s) read from files; fusing {len(fused)} from "
        f"{fpf} frames each at a {fusion.tsdf_voxel} m TSDF voxel")
    t0 = time.perf_counter()
    for fs in tqdm(sorted(fused, key=lambda f: (f.scene, f.index)), desc="fuse", unit="fragment"):
        clouds, _ = fuse_sequence(layout, fs.scene, fs.seq, fs.frames, len(fs.frames), fusion, first_index=fs.index)
        points[(fs.scene, fs.index)] = len(clouds[0])
    fuse_s = time.perf_counter() - t0
    if fused:
        log(f"[prepare] threedmatch: fused {len(fused)} fragment(s) in {fuse_s:.1f} s ({fuse_s / len(fused):.1f} s each)")

    _write_benchmarks(layout, plan)
    write_split(layout.split_file("test"), scenes)
    for split in ("train", "val"):
        write_split(layout.split_file(split), [])
        write_pairs(layout.pairs_file(split), [])
    pts = list(points.values())
    kept = {b: sum(len(o.pairs) for o in plan.kept[b].values()) for b in BENCHMARKS}
    log(f"[prepare] threedmatch: {len(scenes)} test scene(s), pairs {kept}")
    return {
        "scenes": {"train": 0, "val": 0, "test": len(scenes)},
        "fragments": len(points),
        "fragments_read": len(read),
        "fragments_fused": len(fused),
        "fusion_seconds": round(fuse_s, 2),
        "points_per_fragment": {"mean": float(np.mean(pts)), "min": int(min(pts)), "max": int(max(pts))},
        "pairs": kept,
        "pairs_dropped": dict(plan.dropped),
        "pairs_official": dict(plan.official),
    }
