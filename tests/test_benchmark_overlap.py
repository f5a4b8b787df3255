"""The overlap diagnosis tool (python -m pcrcg.benchmarks.overlap): its labels, AUC and score swaps."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pcrcg.benchmarks.overlap import auc, overlap_labels, sampling_variants, with_scores
from pcrcg.geometry import make_transform
from pcrcg.models.module import PairOutput
from pcrcg.registration.feature_registration import FragmentOutput


def test_auc_orders_scores():
    labels = np.array([0, 0, 1, 1, 0, 1], bool)
    assert auc(labels.astype(float), labels) == 1.0
    assert auc(-labels.astype(float), labels) == 0.0
    assert auc(np.ones(6), labels) == 0.5  # ties count half
    assert auc(np.array([0.1, 0.4, 0.35, 0.8]), np.array([0, 0, 1, 1], bool)) == 0.75
    assert np.isnan(auc(np.arange(3.0), np.ones(3, bool)))


def _pair(shift: float = 1.0) -> PairOutput:
    """Two grids of 20 x 10 points 0.1 m apart, the same in their own frames; the ground-truth motion moves
    the source by -``shift`` m in x, so with shift 1.0 half of each fragment (10 of 20 columns) overlaps."""
    g = np.stack(np.meshgrid(np.arange(20) * 0.1, np.arange(10) * 0.1, [0.0], indexing="ij"), -1).reshape(-1, 3)
    T = make_transform(np.eye(3), np.array([-shift, 0.0, 0.0]))  # src -> tgt
    rng = np.random.default_rng(0)

    def frag(p):  # noqa: ANN001, ANN202
        return FragmentOutput(p, rng.normal(size=(len(p), 8)).astype(np.float32), rng.random(len(p)), rng.random(len(p)))

    return PairOutput("s", 0, 1, frag(g.astype(np.float32)), frag(g.astype(np.float32)), T)


def test_overlap_labels_follow_the_ground_truth_motion():
    p = _pair()
    ls, lt = overlap_labels(p.src.points, p.tgt.points, p.transform, radius=0.05)
    assert ls.sum() == lt.sum() == 100
    assert ls[p.src.points[:, 0] > 0.95].all() and not ls[p.src.points[:, 0] < 0.95].any()  # x - 1 within [0, 1.9]
    assert lt[p.tgt.points[:, 0] < 0.95].all() and not lt[p.tgt.points[:, 0] > 0.95].any()
    far = overlap_labels(p.src.points, p.tgt.points, make_transform(np.eye(3), np.array([5.0, 0, 0])), 0.05)
    assert not far[0].any() and not far[1].any()


def test_with_scores_and_the_oracle_variant():
    p = _pair(shift=1.0)
    q = with_scores(p, np.zeros(200), np.linspace(0, 1, 200), floor=1e-3)
    assert q.src.overlap.min() == pytest.approx(1e-3) and (q.src.matchability == 1).all()
    assert np.array_equal(q.src.descriptors, p.src.descriptors) and (q.scene, q.i, q.j) == (p.scene, p.i, p.j)
    assert p.src.overlap.max() < 1.0  # the original is untouched
    v = sampling_variants([p], radius=0.05)
    assert set(v) == {"model", "true overlap (oracle)", "uniform"} and v["model"][0] is p
    ls, _ = overlap_labels(p.src.points, p.tgt.points, p.transform, 0.05)
    assert np.array_equal(v["true overlap (oracle)"][0].src.overlap > 0.5, ls)
    assert (v["uniform"][0].tgt.overlap == 1).all()


def test_missing_checkpoint_is_one_line_and_exit_2(tmp_path):
    missing = tmp_path / "nowhere" / "model.ckpt"
    proc = subprocess.run([sys.executable, "-m", "pcrcg.benchmarks.overlap", str(missing)], capture_output=True, text=True)
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("pcrcg.benchmarks.overlap: error: ") and str(missing) in lines[0]
