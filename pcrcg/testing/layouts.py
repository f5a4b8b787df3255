"""A tiny data set in the 3DMatch layout, cut from the fixtures' box room (tests and benchmarks;
never used by a run)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pcrcg.geometry import invert, make_transform, random_rotation, transform_points
from pcrcg.testing.pairs import voxel_crop
from pcrcg.testing.rooms import box_room


def write_layout(root: str | Path, seed: int = 0, scene: str = "room", n_fragments: int = 5,
                 voxel: float = 0.03, n_points: int = 20000) -> Path:
    """A tiny data set in the 3DMatch layout: ``n_fragments`` overlapping crops of one room,
    each in its own frame, and 3DMatch / 3DLoMatch benchmark files (all pairs i < j split by
    overlap at 30 %; info matrices from the true overlap). Returns the root."""
    from scipy.spatial import cKDTree

    from pcrcg.data.layout import Layout, PairRecord, write_gt_info, write_gt_log, write_gt_overlap, write_ply, write_split
    from pcrcg.evaluation.metrics import information_matrix

    rng = np.random.default_rng(seed)
    pts, cols = box_room(rng, n_points)
    layout = Layout(root)
    layout.fragments_dir(scene).mkdir(parents=True, exist_ok=True)
    lo, hi = pts[:, 0].min(), pts[:, 0].max()
    width = 0.5 * (hi - lo)  # 5 fragments: neighbours overlap ~75 %, i/i+2 ~50 %, i/i+3 ~25 %
    frags = []
    for f in range(n_fragments):
        a = lo + (hi - lo - width) * f / max(n_fragments - 1, 1)
        m = (pts[:, 0] >= a) & (pts[:, 0] <= a + width)
        w, c = voxel_crop(pts[m], cols[m], voxel)
        A = make_transform(random_rotation(rng, np.pi / 3), rng.normal(scale=0.3, size=3)) @ make_transform(np.eye(3), -w.mean(0))
        write_ply(layout.fragment(scene, f), transform_points(A, w), c)
        frags.append((w, A))
    recs = {"3DMatch": [], "3DLoMatch": []}
    infos = {"3DMatch": [], "3DLoMatch": []}
    for i in range(n_fragments):
        for j in range(i + 1, n_fragments):
            wi, Ai = frags[i]
            wj, Aj = frags[j]
            d, _ = cKDTree(wi).query(wj)
            ov_j = d < 1.5 * voxel
            ov = float(min(ov_j.mean(), (cKDTree(wj).query(wi)[0] < 1.5 * voxel).mean()))
            if ov < 0.05:
                continue
            b = "3DMatch" if ov > 0.3 else "3DLoMatch"
            recs[b].append(PairRecord(scene, i, j, Ai @ invert(Aj), ov, n_fragments))
            infos[b].append(information_matrix(transform_points(Aj, wj[ov_j])))
    for b in recs:
        d = layout.benchmark_dir(b, scene)
        d.mkdir(parents=True, exist_ok=True)
        write_gt_log(d / "gt.log", recs[b])
        write_gt_info(d / "gt.info", recs[b], infos[b])
        write_gt_overlap(d / "gt_overlap.log", recs[b])
    write_split(layout.split_file("test"), [scene])
    return Path(root)
