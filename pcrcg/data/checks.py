"""Consistency checks of a data set in the layout, beyond "the files are there".

``python -m pcrcg.data.checks ROOT`` prints one line per check and exits non-zero on failure:

* layout: splits, fragments, info files, frames, intrinsics, benchmark files all present;
* pose/gt.log agreement: each ``gt.log`` / pairs transform equals inv(P_i) P_j from the frames'
  poses (first frame of each fragment), where frames are available;
* overlap: recomputed overlaps match ``gt_overlap.log`` / the pairs files;
* gt.info: recomputed information matrices match ``gt.info``;
* depth agreement: a fragment's points projected into its first frame agree with that frame's
  depth map (median |dz| small) — the fragment really is in that camera's frame.

The overlap and gt.info checks re-derive what *this project's* data code wrote (generated rooms,
``data=redkitchen``), with independent implementations of the same definitions. Benchmark files this
project did not write cannot be re-derived that way: ``data=threedmatch`` copies the official release's
``gt.log`` / ``gt.info`` / ``gt_overlap.log``, which 3DMatch's own code made (its overlaps and information
matrices from its own clouds and sampling). The manifest says who wrote a data set's benchmark files
(:func:`benchmark_writer`); for such files those two checks are reported as not applicable (``n/a``),
not as failures, and the pose check allows the release builder's tolerance
(:data:`pcrcg.data.release.POSE_TOLERANCE`) instead of this project's round-off.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pcrcg.data.layout import (
    BENCHMARKS,
    SPLITS,
    Layout,
    PairRecord,
    frame_paths,
    read_cloud,
    read_depth,
    read_fragment_info,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
    read_intrinsics,
    read_pairs,
    read_pose,
)
from pcrcg.data.materialise import read_manifest
from pcrcg.data.pairs import MAX_INFO_POINTS, OVERLAP_RADIUS, voxel_downsample
from pcrcg.errors import DataError
from pcrcg.geometry import invert, project


# who wrote the benchmark files of a data set, by the data source named in its manifest (params.name);
# a source not listed here is this project's own data code
FOREIGN_WRITERS = {"threedmatch": "3DMatch's code"}
OWN_POSE_TOLERANCE = 1e-6  # gt.log written by this project from the frames' poses: round-off only


@dataclass
class CheckReport:
    passed: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    not_applicable: list[str] = field(default_factory=list)  # checks that cannot judge these files
    measures: dict[str, float] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.failed


def check_layout(root: str | Path) -> list[str]:
    """Every file the layout promises; returns the missing paths (empty when complete)."""
    layout = Layout(root)
    missing = []
    if not layout.root.is_dir():
        return [str(layout.root)]
    for split in SPLITS:
        if not layout.split_file(split).is_file():
            missing.append(str(layout.split_file(split)))
    if missing:
        return missing
    scenes = [s for sp in SPLITS for s in layout.scenes(sp)]
    for scene in scenes:
        d = layout.fragments_dir(scene)
        if not d.is_dir():
            missing.append(str(d))
            continue
        for ply in sorted(d.glob("cloud_bin_*.ply")):
            i = int(ply.stem.split("_")[-1])
            info = layout.fragment_info(scene, i)
            if not info.is_file():
                continue  # fragments without frames (e.g. a .pth release) have no views
            fi = read_fragment_info(info)
            if not layout.intrinsics(scene).is_file():
                missing.append(str(layout.intrinsics(scene)))
            for fid in (fi.first_frame, fi.last_frame, (fi.first_frame + fi.last_frame) // 2):
                for p in frame_paths(layout.frame_prefix(scene, fi.seq, fid)):
                    if not p.is_file():
                        missing.append(str(p))
    for scene in layout.scenes("test"):
        for b in BENCHMARKS:
            for f in ("gt.log", "gt.info", "gt_overlap.log"):
                p = layout.benchmark_dir(b, scene) / f
                if not p.is_file():
                    missing.append(str(p))
    return sorted(set(missing))


def _first_pose(layout: Layout, scene: str, i: int) -> np.ndarray | None:
    p = layout.fragment_info(scene, i)
    if not p.is_file():
        return None
    fi = read_fragment_info(p)
    return read_pose(frame_paths(layout.frame_prefix(scene, fi.seq, fi.first_frame))[2])


def benchmark_writer(root: str | Path) -> str | None:
    """Who wrote the benchmark files (``gt.log``, ``gt.info``, ``gt_overlap.log``) of the data set at ``root``,
    from its ``manifest.json``: None for this project's data code (or no manifest: nothing says otherwise),
    else a name, e.g. ``"3DMatch's code"`` for ``data=threedmatch`` (its builder records the release as its
    ``source`` and copies the official files)."""
    params = (read_manifest(Path(root)) or {}).get("params") or {}
    name = params.get("name", params.get("source"))
    return FOREIGN_WRITERS.get(name) if isinstance(name, str) else None


@dataclass
class _Record:
    """One pair to check: where it is listed, its gt.log / pairs record, and the overlap and information
    matrix (6, 6) the files give for it (None: not to be re-derived)."""

    where: str
    pair: PairRecord
    overlap: float | None
    info: np.ndarray | None


def _records(layout: Layout, foreign: bool, max_pairs: int) -> list[_Record]:
    """The benchmarks' and the training pairs' records, at most ``max_pairs``; a foreign writer's overlaps
    and information matrices are left out (None)."""
    records = []
    for scene in layout.scenes("test"):
        for b in BENCHMARKS:
            d = layout.benchmark_dir(b, scene)
            ov = {} if foreign else read_gt_overlap(d / "gt_overlap.log")
            info = {} if foreign else read_gt_info(d / "gt.info")
            for r in read_gt_log(d / "gt.log", scene):
                records.append(_Record(b, r, ov.get((r.i, r.j)), info.get((r.i, r.j))))
    for split in ("train", "val"):
        for r in read_pairs(layout.pairs_file(split)):
            records.append(_Record(split, r, r.overlap, None))
    return records[:max_pairs]


def check_dataset(root: str | Path, max_pairs: int = 200, overlap_voxel: float = 0.025) -> CheckReport:
    """Run all checks; returns a report (``ok``, messages, and the worst measured deviations)."""
    rep = CheckReport()
    layout = Layout(root)
    missing = check_layout(root)
    if missing:
        rep.failed.append(f"layout: {len(missing)} missing, first {missing[0]}")
        return rep
    rep.passed.append("layout complete")
    writer = benchmark_writer(root)
    records = _records(layout, writer is not None, max_pairs)
    _check_pairs(rep, layout, records, writer, overlap_voxel)
    _check_depth(rep, layout)
    return rep


def _check_pairs(rep: CheckReport, layout: Layout, records: list[_Record], writer: str | None,
                 overlap_voxel: float) -> None:
    """Pose/gt.log agreement, and the overlaps and gt.info re-derived, over ``records``."""
    cache: dict[tuple[str, int], np.ndarray] = {}

    def cloud(scene, i):
        if (scene, i) not in cache:
            cache[(scene, i)] = voxel_downsample(read_cloud(layout.fragment(scene, i))[0].astype(np.float64), overlap_voxel)
        return cache[(scene, i)]

    pose_err = ov_err = info_err = 0.0
    n_pose = n_ov = n_info = 0
    for rec in records:
        r = rec.pair
        Pi, Pj = _first_pose(layout, r.scene, r.i), _first_pose(layout, r.scene, r.j)
        if Pi is not None and Pj is not None:
            pose_err = max(pose_err, float(np.abs(invert(Pi) @ Pj - r.transform).max()))
            n_pose += 1
        if rec.overlap is not None and np.isfinite(rec.overlap):
            ov2 = independent_overlap(cloud(r.scene, r.i), cloud(r.scene, r.j), r.transform, OVERLAP_RADIUS)
            ov_err = max(ov_err, abs(ov2 - rec.overlap))
            n_ov += 1
        if rec.info is not None:
            info2 = independent_info(cloud(r.scene, r.i), cloud(r.scene, r.j), r.transform, OVERLAP_RADIUS,
                                     seed=r.i * 100003 + r.j)
            info_err = max(info_err, float(np.abs(info2 - rec.info).max() / max(1.0, np.abs(rec.info).max())))
            n_info += 1
    rep.measures.update(pose_max_abs=pose_err, overlap_max_abs=ov_err, info_max_rel=info_err)
    tolerance, whose = _pose_tolerance(writer)
    _verdict(rep, n_pose and pose_err < tolerance,
             f"pose/gt agreement over {n_pose} pairs (max |dT| {pose_err:.2e}, tolerance {tolerance:.0e}{whose})")
    if n_ov or writer is None:  # a foreign writer's data set may still hold this project's training pairs
        _verdict(rep, ov_err < 0.02, f"overlaps recomputed over {n_ov} pairs (max |d| {ov_err:.4f})")
    if writer is None:
        _verdict(rep, info_err < 1e-3, f"gt.info recomputed over {n_info} pairs (max relative diff {info_err:.2e})")
    else:
        for what in ("benchmark overlaps (gt_overlap.log)", "gt.info"):
            rep.not_applicable.append(f"{what}: not applicable: written by {writer}, not this project's")


def _pose_tolerance(writer: str | None) -> tuple[float, str]:
    """The pose check's tolerance (max |inv(P_i) P_j - gt| entry) and a note saying whose gt.log it is."""
    if writer is None:
        return OWN_POSE_TOLERANCE, ""
    from pcrcg.data.release import POSE_TOLERANCE

    return POSE_TOLERANCE, f": gt.log written by {writer}, the release builder's tolerance"


def _check_depth(rep: CheckReport, layout: Layout) -> None:
    """Depth agreement on each test scene's first fragments (and one training scene's)."""
    med = []
    for scene in layout.scenes("test") + layout.scenes("train")[:1]:
        K = read_intrinsics(layout.intrinsics(scene)) if layout.intrinsics(scene).is_file() else None
        if K is None:
            continue
        for i in range(min(3, layout.n_fragments(scene))):
            if not layout.fragment_info(scene, i).is_file():
                continue
            fi = read_fragment_info(layout.fragment_info(scene, i))
            depth = read_depth(frame_paths(layout.frame_prefix(scene, fi.seq, fi.first_frame))[1])
            pts = read_cloud(layout.fragment(scene, i))[0].astype(np.float64)
            med.append(depth_agreement(pts, depth, K))
    if med:
        worst = float(np.nanmax(med))
        rep.measures["depth_median_abs_max"] = worst
        _verdict(rep, worst < 0.03, f"depth agreement over {len(med)} fragments (worst median |dz| {worst * 100:.2f} cm)")


def _o3d_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (N,) of each point of a (N, 3) to its nearest point of b (M, 3), by Open3D (not the
    SciPy KD-tree the data code uses)."""
    import open3d as o3d

    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(a, np.float64)))
    pb = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(b, np.float64)))
    return np.asarray(pa.compute_point_cloud_distance(pb))


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]


def independent_overlap(pts_i: np.ndarray, pts_j: np.ndarray, T_ji: np.ndarray, radius: float) -> float:
    """The overlap of ``gt_overlap.log`` (the larger share of either fragment within ``radius`` of the
    other, j mapped into i), recomputed without the data code's functions."""
    pj = _apply(T_ji, pts_j)
    return float(max(np.mean(_o3d_distances(pj, pts_i) < radius), np.mean(_o3d_distances(pts_i, pj) < radius)))


def independent_info(pts_i: np.ndarray, pts_j: np.ndarray, T_ji: np.ndarray, radius: float, seed: int,
                     max_points: int = MAX_INFO_POINTS) -> np.ndarray:
    """``gt.info`` recomputed with the evaluation's information matrix
    (:func:`pcrcg.evaluation.metrics.information_matrix`) on the points of i within ``radius`` of the
    aligned j (the same subsample of at most ``max_points``, drawn with ``seed``)."""
    from pcrcg.evaluation.metrics import information_matrix

    p = np.asarray(pts_i, np.float64)[_o3d_distances(pts_i, _apply(T_ji, pts_j)) < radius]
    if len(p) > max_points:
        p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
    return information_matrix(p)


def depth_agreement(points: np.ndarray, depth: np.ndarray, K: np.ndarray) -> float:
    """Median |z - depth(u, v)| over the points (N, 3) that project onto valid depth pixels and are
    not occluded (z within 10 cm of the depth); NaN when none do."""
    uv, z = project(points, K)
    H, W = depth.shape
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    m = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    d = depth[v[m], u[m]]
    dz = np.abs(z[m] - d)[d > 0]
    dz = dz[dz < 0.10]
    return float(np.median(dz)) if len(dz) else float("nan")


def _verdict(rep: CheckReport, ok, msg: str) -> None:
    (rep.passed if ok else rep.failed).append(msg)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root")
    a = ap.parse_args(argv)
    try:
        rep = check_dataset(a.root)
    except DataError as exc:
        print(f"FAIL {exc}")
        return 1
    for m in rep.passed:
        print(f"ok   {m}")
    for m in rep.not_applicable:
        print(f"n/a  {m}")
    for m in rep.failed:
        print(f"FAIL {m}")
    return 0 if rep.ok else 1


if __name__ == "__main__":
    sys.exit(main())
