"""What a column of the statistics table reads: a data set in the 3DMatch layout, or bare folders.

* :func:`open_root` — a root in the layout (``fragments/<scene>/cloud_bin_<i>.ply`` and
  optionally ``.info.txt``, ``rgbd/``, ``benchmarks/``, ``pairs/train.txt``); a missing root or
  one without fragments is a :class:`~pcrcg.errors.DataError` naming it.
* :func:`open_folder` — a bare folder of ``cloud_bin_<i>.{ply,pcd,npz,pth}`` (one scene, named
  after the folder), optionally with a folder of RGB-D frames (``frame-XXXXXX.color.{png,jpg}``,
  ``.depth.png``, either directly or under ``<seq>/``) and a benchmarks folder
  (``<dir>/{3DMatch,3DLoMatch}/<scene>/gt.log|gt.info|gt_overlap.log``, e.g. the official files).

Both are checked before any measure starts; nothing is written.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pcrcg.data.layout import evenly  # noqa: F401  (re-exported for the stats package)
from pcrcg.data.layout import (
    BENCHMARKS,
    FragmentInfo,
    PairRecord,
    read_fragment_info,
    read_gt_log,
    read_gt_overlap,
    read_pairs,
)
from pcrcg.errors import DataError

CLOUD_SUFFIXES = (".ply", ".pcd", ".npz", ".pth")
_BIN = re.compile(r"^cloud_bin_(\d+)$")


@dataclass(frozen=True)
class FragmentRef:
    """One fragment file: ``scene``, index ``i`` (``cloud_bin_<i>``) and its path."""

    scene: str
    index: int
    path: Path


@dataclass
class Source:
    """One column: fragments, their frame ranges, frames, benchmark pairs and training pairs."""

    name: str
    path: Path
    kind: str  # "layout" | "folder"
    fragments: list[FragmentRef]
    infos: dict[tuple[str, int], FragmentInfo] = field(default_factory=dict)
    rgbd_dirs: dict[str, Path] = field(default_factory=dict)  # scene -> folder of <seq>/frame-*
    flat_frames: dict[str, Path] = field(default_factory=dict)  # scene -> folder of frame-* (no seq level)
    benchmark_dirs: dict[str, dict[str, Path]] = field(default_factory=dict)  # benchmark -> scene -> dir
    train_pairs: Path | None = None
    _by_key: dict[tuple[str, int], FragmentRef] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self._by_key = {(f.scene, f.index): f for f in self.fragments}

    # ----------------------------------------------------------------- lookups

    def fragment(self, scene: str, i: int) -> FragmentRef | None:
        return self._by_key.get((scene, i))

    @property
    def has_frames(self) -> bool:
        return bool(self.rgbd_dirs or self.flat_frames)

    def frame_prefix(self, scene: str, seq: str, frame: int) -> Path | None:
        """``.../frame-XXXXXX`` of a frame, or None when the scene has no frames folder."""
        if scene in self.flat_frames:
            return self.flat_frames[scene] / f"frame-{frame:06d}"
        if scene in self.rgbd_dirs:
            return self.rgbd_dirs[scene] / seq / f"frame-{frame:06d}"
        return None

    def benchmark_pairs(self, benchmark: str) -> list[PairRecord]:
        """Every pair listed in the benchmark's ``gt.log`` files (scene order), with its overlap from
        ``gt_overlap.log`` (NaN when not listed there)."""
        out = []
        for scene, d in sorted(self.benchmark_dirs.get(benchmark, {}).items()):
            recs = read_gt_log(d / "gt.log", scene)
            ov_file = d / "gt_overlap.log"
            ov = read_gt_overlap(ov_file) if ov_file.is_file() else {}
            out += [PairRecord(scene, r.i, r.j, r.transform, ov.get((r.i, r.j), float("nan")), r.n_fragments)
                    for r in recs]
        return out

    def train_overlaps(self) -> list[float] | None:
        if self.train_pairs is None:
            return None
        return [p.overlap for p in read_pairs(self.train_pairs)]


# --------------------------------------------------------------------------- discovery


def _fragment_files(folder: Path, scene: str, suffixes=CLOUD_SUFFIXES) -> list[FragmentRef]:
    """``cloud_bin_<i>.<suffix>`` of a folder by index (a ``.ply`` wins over the other formats)."""
    best: dict[int, Path] = {}
    for p in folder.glob("cloud_bin_*"):
        if p.suffix.lower() not in suffixes or not p.is_file():
            continue
        m = _BIN.match(p.stem)
        if not m:
            continue
        i = int(m.group(1))
        if i not in best or suffixes.index(p.suffix.lower()) < suffixes.index(best[i].suffix.lower()):
            best[i] = p
    return [FragmentRef(scene, i, best[i]) for i in sorted(best)]


def _infos(folder: Path, refs: list[FragmentRef]) -> dict[tuple[str, int], FragmentInfo]:
    out = {}
    for f in refs:
        p = folder / f"cloud_bin_{f.index}.info.txt"
        if p.is_file():
            out[(f.scene, f.index)] = read_fragment_info(p)
    return out


def open_root(path: str | Path, name: str | None = None) -> Source:
    """A data set in the 3DMatch layout (README, "The data layout")."""
    root = Path(path)
    if not root.is_dir():
        raise DataError(root, "data root does not exist")
    fdir = root / "fragments"
    refs: list[FragmentRef] = []
    infos: dict[tuple[str, int], FragmentInfo] = {}
    if fdir.is_dir():
        for sd in sorted(d for d in fdir.iterdir() if d.is_dir()):
            r = _fragment_files(sd, sd.name, (".ply",))
            refs += r
            infos.update(_infos(sd, r))
    if not refs:
        raise DataError(root, "not a data set in the 3DMatch layout (no fragments/<scene>/cloud_bin_<i>.ply; "
                              "make one with `python -m pcrcg.prepare`, or use --fragments-dir for a bare folder)")
    scenes = sorted({f.scene for f in refs})
    rgbd = {s: root / "rgbd" / s for s in scenes if (root / "rgbd" / s).is_dir()}
    bench = {}
    for b in BENCHMARKS:
        bd = root / "benchmarks" / b
        found = {d.name: d for d in sorted(bd.iterdir()) if (d / "gt.log").is_file()} if bd.is_dir() else {}
        if found:
            bench[b] = found
    train = root / "pairs" / "train.txt"
    return Source(name or root.resolve().name, root, "layout", refs, infos, rgbd, {}, bench,
                  train if train.is_file() else None)


def open_folder(
    fragments_dir: str | Path,
    frames_dir: str | Path | None = None,
    benchmarks_dir: str | Path | None = None,
    frames_per_fragment: int | None = None,
    name: str | None = None,
) -> Source:
    """A bare folder of fragments (one scene: the folder's name), with optional frames and benchmarks.

    A fragment's frames come from its ``cloud_bin_<i>.info.txt``; where there is none and
    ``frames_per_fragment`` (N) is given, fragment i is taken to hold frames N*i ... N*i + N - 1
    (how 3DMatch made its fragments: 50 frames each).
    """
    fdir = Path(fragments_dir)
    if not fdir.is_dir():
        raise DataError(fdir, "fragments folder (--fragments-dir) does not exist")
    scene = fdir.resolve().name
    refs = _fragment_files(fdir, scene)
    if not refs:
        raise DataError(fdir, "holds no fragments (cloud_bin_<i>.ply|.pcd|.npz|.pth)")
    infos = _infos(fdir, refs)
    if frames_per_fragment:
        n = int(frames_per_fragment)
        if n < 1:
            raise DataError(fdir, f"--frames-per-fragment must be >= 1, got {n}")
        seq = next((inf.seq for inf in infos.values()), "seq-01")
        for f in refs:
            infos.setdefault((scene, f.index), FragmentInfo(scene, seq, n * f.index, n * f.index + n - 1))
    flat, rgbd = {}, {}
    if frames_dir is not None:
        d = Path(frames_dir)
        if not d.is_dir():
            raise DataError(d, "frames folder (--frames-dir) does not exist")
        if any(d.glob("frame-*.depth.png")):
            flat[scene] = d
        elif any(d.glob("*/frame-*.depth.png")):
            rgbd[scene] = d
        else:
            raise DataError(d, "holds no RGB-D frames (frame-XXXXXX.depth.png, directly or under <seq>/)")
    bench = {}
    if benchmarks_dir is not None:
        bd = Path(benchmarks_dir)
        if not bd.is_dir():
            raise DataError(bd, "benchmarks folder (--benchmarks-dir) does not exist")
        for b in BENCHMARKS:
            d = bd / b / scene
            if (d / "gt.log").is_file():
                bench[b] = {scene: d}
        if not bench:
            raise DataError(bd, f"holds no {'|'.join(BENCHMARKS)}/{scene}/gt.log")
    return Source(name or f"{scene} (folder)", fdir, "folder", refs, infos, rgbd, flat, bench, None)


# --------------------------------------------------------------------------- frames


def color_path(prefix: Path) -> Path | None:
    """The color image of a frame prefix: ``.color.png`` or, failing that, ``.color.jpg``."""
    for ext in (".color.png", ".color.jpg"):
        p = prefix.with_name(prefix.name + ext)
        if p.is_file():
            return p
    return None


def depth_path(prefix: Path) -> Path | None:
    p = prefix.with_name(prefix.name + ".depth.png")
    return p if p.is_file() else None


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a PNG (the layout's checked reader) or a JPEG."""
    from pcrcg.data.layout import read_color

    if path.suffix.lower() == ".png":
        return read_color(path)
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(path, "cannot decode the color image")
    return np.ascontiguousarray(img[:, :, ::-1])


