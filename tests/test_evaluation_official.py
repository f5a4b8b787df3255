"""The official 3DMatch / 3DLoMatch benchmark files (../shared), and an independent second
implementation of the registration-recall protocol that must agree with ours."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pcrcg.evaluation.metrics import counted_mask, load_benchmark, score_benchmark

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
BENCH = SHARED / "data" / "3dmatch-benchmarks"
EXPECTED = {"3DMatch": (1623, 1279), "3DLoMatch": (1781, 1726)}

pytestmark = pytest.mark.shared


@pytest.fixture(scope="module")
def official():
    if not BENCH.is_dir():
        pytest.skip(f"{BENCH} is not available")
    return {b: load_benchmark(BENCH / b) for b in EXPECTED}


def test_official_files_parse_with_the_published_pair_counts(official):
    for b, (n_pairs, n_counted) in EXPECTED.items():
        gt = official[b]
        assert len(gt) == 8
        assert sum(len(g.pairs) for g in gt.values()) == n_pairs
        assert sum(int(counted_mask(g.pairs).sum()) for g in gt.values()) == n_counted


def test_ground_truth_as_estimate_on_official_files(official):
    m = score_benchmark(official["3DMatch"], {s: dict(zip(g.keys(), g.transforms)) for s, g in official["3DMatch"].items()})
    assert m.rr == 100.0 and m.n_success == 1279
    # 3DLoMatch holds one pair whose gt.info matrix is all zeros (home_md 23 25): it can never pass
    lo = official["3DLoMatch"]
    m = score_benchmark(lo, {s: dict(zip(g.keys(), g.transforms)) for s, g in lo.items()})
    assert m.n_success == 1725 and m.n_counted == 1726
    assert m.scenes["sun3d-home_md-home_md_scan9_2012_sep_30"] == pytest.approx(100 * 221 / 222)


# --------------------------------------------------------------------------- second implementation


def _read_log(path: Path):
    """Plain re-implementation of the gt.log / est.log reader: [(i, j), 4x4]."""
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    return [((int(rows[k][0]), int(rows[k][1])), np.array(rows[k + 1:k + 5], float)) for k in range(0, len(rows), 5)]


def _read_info(path: Path):
    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    return {(int(rows[k][0]), int(rows[k][1])): np.array(rows[k + 1:k + 7], float) for k in range(0, len(rows), 7)}


def _reference_recall(bench_dir: Path, estimates: dict) -> tuple[float, float]:
    """Per-pair loop with SciPy quaternions: (scene-averaged recall %, pooled recall %)."""
    per_scene, good_all, n_all = [], 0, 0
    for scene_dir in sorted(p for p in bench_dir.iterdir() if p.is_dir()):
        gt = _read_log(scene_dir / "gt.log")
        info = _read_info(scene_dir / "gt.info")
        good = n = 0
        for (i, j), T_gt in gt:
            if j - i <= 1:
                continue
            n += 1
            T_est = estimates[scene_dir.name].get((i, j))
            if T_est is None:
                continue
            D = np.linalg.solve(T_gt, T_est)
            x, y, z, w = Rotation.from_matrix(D[:3, :3]).as_quat()
            if w < 0:
                x, y, z = -x, -y, -z
            e = np.array([D[0, 3], D[1, 3], D[2, 3], x, y, z])
            M = info[(i, j)]
            if M[0, 0] > 0 and float(e @ M @ e) / M[0, 0] <= 0.04:
                good += 1
        per_scene.append(100.0 * good / n)
        good_all += good
        n_all += n
    return float(np.mean(per_scene)), 100.0 * good_all / n_all


@pytest.mark.parametrize("benchmark", list(EXPECTED))
def test_recall_equals_an_independent_implementation(official, benchmark):
    rng = np.random.default_rng(0)
    gt = official[benchmark]
    est = {}
    for s, g in gt.items():
        est[s] = {}
        for (i, j), T in zip(g.keys(), g.transforms):
            if rng.random() < 0.03:
                continue  # missing estimate
            # perturbations around the threshold: about half of the pairs pass
            R = Rotation.from_rotvec(rng.normal(size=3) * rng.uniform(0, 0.12)).as_matrix()
            D = np.eye(4)
            D[:3, :3] = R
            D[:3, 3] = rng.normal(size=3) * rng.uniform(0, 0.15)
            est[s][(i, j)] = T @ D
    ours = score_benchmark(gt, est)
    ref_rr, ref_pair = _reference_recall(BENCH / benchmark, est)
    assert 20.0 < ours.rr < 80.0  # a meaningful mix of passes and failures
    assert abs(ours.rr - ref_rr) < 0.01
    assert abs(ours.rr_pair - ref_pair) < 0.01
