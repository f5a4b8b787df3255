"""The overlap diagnosis tool (python -m pcrcg.benchmarks.overlap): its labels, AUC and score swaps."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from pcrcg.benchmarks.overlap import (
    auc,
    cue_table,
    descriptor_agreement,
    overlap_labels,
    sampling_variants,
    single_fragment_cues,
    with_scores,
)
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
    assert set(v) == {"model", "overlap head alone", "true overlap (oracle)", "uniform"} and v["model"][0] is p
    assert np.allclose(v["overlap head alone"][0].src.overlap, np.maximum(p.src.overlap, 1e-3))
    assert (v["overlap head alone"][0].src.matchability == 1).all()
    ls, _ = overlap_labels(p.src.points, p.tgt.points, p.transform, 0.05)
    assert np.array_equal(v["true overlap (oracle)"][0].src.overlap > 0.5, ls)
    assert (v["uniform"][0].tgt.overlap == 1).all()


def test_missing_checkpoint_is_one_line_and_exit_2(tmp_path):
    missing = tmp_path / "nowhere" / "model.ckpt"
    proc = subprocess.run([sys.executable, "-m", "pcrcg.benchmarks.overlap", str(missing)], capture_output=True, text=True)
    lines = [x for x in proc.stderr.splitlines() if x.strip()]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith("pcrcg.benchmarks.overlap: error: ") and str(missing) in lines[0]


def test_descriptor_agreement_scores_points_with_a_partner_higher():
    rng = np.random.default_rng(1)
    shared = rng.normal(size=(30, 16))
    src = np.concatenate([shared, rng.normal(size=(50, 16))])  # 30 with a partner, 50 without
    tgt = np.concatenate([shared[::-1] + 0.01 * rng.normal(size=(30, 16)), rng.normal(size=(40, 16))])
    src = (src / np.linalg.norm(src, axis=1, keepdims=True)).astype(np.float32)
    tgt = (tgt / np.linalg.norm(tgt, axis=1, keepdims=True)).astype(np.float32)
    ag = descriptor_agreement(src, tgt, chunk=7)  # chunks that do not divide the rows
    truth_s, truth_t = np.arange(80) < 30, np.arange(70) < 30
    for name in ("similarity", "ratio"):
        s, t = ag[name]
        assert s.shape == (80,) and t.shape == (70,)
        assert auc(s, truth_s) == 1.0 and auc(t, truth_t) == 1.0, name
    s, _ = ag["similarity"]
    assert np.allclose(s[:30], (1 + (src[:30] @ tgt.T).max(1)) / 2) and s.max() <= 1.0 + 1e-6
    r, _ = ag["ratio"]
    assert (r >= 0).all() and (r <= 1).all() and r[:30].min() > 0.8  # a near-copy is far nearer than the next
    p = _pair()
    ag = descriptor_agreement(p.src.descriptors, p.tgt.descriptors)
    v = sampling_variants([p], radius=0.05, agreement=[ag])
    assert {"descriptor similarity", "descriptor ratio"} <= set(v)
    assert np.allclose(v["descriptor ratio"][0].src.overlap, np.maximum(ag["ratio"][0], 1e-3))


def test_single_fragment_cues_and_their_table():
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [3.0, 0.0, 4.0], [0.0, -1.0, 1.0]])
    c = single_fragment_cues(pts)
    assert set(c) == {"periphery", "camera y (down)", "range", "depth"}
    assert np.allclose(c["range"], [1.0, np.sqrt(2), 5.0, np.sqrt(2)])
    assert np.allclose(c["camera y (down)"], pts[:, 1]) and np.allclose(c["depth"], pts[:, 2])
    assert np.allclose(c["periphery"], np.linalg.norm(pts - [0.75, 0.0, 1.75], axis=1))
    # the half-overlapping grids: the source's overlap is its x > 0.95 half, the target's its x < 0.95 half;
    # a head scoring by x - mean(x) follows neither y (flat) nor periphery (symmetric) and is 1 / 0 against truth
    p = _pair()
    xs, xt = p.src.points[:, 0], p.tgt.points[:, 0]
    q = with_scores(p, (xs - xs.min()) / np.ptp(xs), (xt - xt.min()) / np.ptp(xt))
    labels = [overlap_labels(p.src.points, p.tgt.points, p.transform, 0.05)]
    t = cue_table([q], labels)
    assert t["periphery"][0] == pytest.approx(0.5) and abs(t["periphery"][1]) < 0.01  # symmetric about the middle
    assert np.isnan(t["depth"][1])  # z is 0 everywhere: no correlation
    assert t["range"][1] > 0.8  # range grows with x on these grids, as the head's scores do
