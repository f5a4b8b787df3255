"""pcrcg.benchmarks.ranking: a failed registration is put down to RANSAC's ranking or to its search."""

import numpy as np
import pytest

from pcrcg.benchmarks.ranking import Tally, diagnose_pair, failure_kind, inlier_count, overlap_fitness, ranking_score
from pcrcg.evaluation.metrics import information_matrix
from pcrcg.registration.feature_registration import FragmentOutput, RegistrationConfig, pair_seed
from pcrcg.registration.ransac import RansacConfig


def _floor(x1: float, y1: float, step: float = 0.05) -> np.ndarray:
    """(n, 3) a floor patch [0, x1] x [0, y1] at z = 0."""
    x, y = np.meshgrid(np.arange(0, x1 + 1e-9, step), np.arange(0, y1 + 1e-9, step))
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)


def _shift(dx=0.0, dy=0.0, dz=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (dx, dy, dz)
    return T


def test_overlap_fitness_and_inlier_count():
    tgt = _floor(2.0, 1.0)
    src = _floor(1.0, 1.0)
    assert overlap_fitness(np.eye(4), src, tgt, 0.03) == 1.0
    assert overlap_fitness(_shift(dz=1.0), src, tgt, 0.03) == 0.0
    assert overlap_fitness(_shift(dx=1.5), src, tgt, 0.03) == pytest.approx(11 / 21)  # half a patch still on the floor
    c = src[:10]
    assert inlier_count(np.eye(4), c, c, 0.01) == 10 and inlier_count(_shift(dx=0.5), c, c, 0.01) == 0
    assert ranking_score("correspondences", np.eye(4), src, tgt, c, c, 0.01) == 10.0
    with pytest.raises(ValueError, match="ranking must be one of"):
        ranking_score("fitness", np.eye(4), src, tgt, c, c, 0.01)


def test_a_pose_slid_along_the_floor_is_a_ranking_failure_one_off_the_floor_a_search_failure():
    """Overlap scores a patch slid along a floor as high as the truth (no budget can fix that); a pose lifted
    off it scores lower (the search stopped short). Inlier correspondences tell the slid pose from the truth."""
    tgt, src = _floor(3.0, 1.0), _floor(1.0, 1.0)
    c = src[::7]  # correct correspondences under the identity
    assert failure_kind("overlap", _shift(dx=1.0), np.eye(4), src, tgt, c, c, 0.03) == "ranking"
    assert failure_kind("overlap", _shift(dz=0.5), np.eye(4), src, tgt, c, c, 0.03) == "search"
    assert failure_kind("correspondences", _shift(dx=1.0), np.eye(4), src, tgt, c, c, 0.03) == "search"


def _pair(rng, noise: float):
    """Two fragments of one random cloud, the target moved by ``T_gt`` (source into target); descriptors shared
    by corresponding points plus ``noise``."""
    pts = rng.uniform(0, 2, (600, 3))
    a = rng.uniform(-np.pi, np.pi)
    T_gt = np.eye(4)
    T_gt[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T_gt[:3, 3] = (0.3, -0.2, 0.1)
    d = rng.normal(size=(600, 16))
    frag = lambda p, dd: FragmentOutput(p, dd / np.linalg.norm(dd, axis=1, keepdims=True), np.ones(600), np.ones(600))  # noqa: E731
    src = frag(pts, d + noise * rng.normal(size=d.shape))
    tgt = frag(pts @ T_gt[:3, :3].T + T_gt[:3, 3], d + noise * rng.normal(size=d.shape))
    return src, tgt, T_gt, information_matrix(pts)


CFG = RegistrationConfig(sampling="prob", fewer_points="with_replacement", n_points=(300,),
                         ransac=RansacConfig(distance=0.05, max_validation=200, confidence=1.0, max_iterations=5000))


def test_both_rankings_register_a_pair_with_good_descriptors_and_the_pair_seed_is_not_consumed():
    src, tgt, T_gt, info = _pair(np.random.default_rng(0), noise=0.0)
    seed = pair_seed(0, "scene", 0, 2, 300)
    assert diagnose_pair(src, tgt, T_gt, info, 300, CFG, seed) == {"overlap": (True, None), "correspondences": (True, None)}
    assert seed.n_children_spawned == 0  # each ranking drew the pair's own samples, not the next ones


def test_every_failure_gets_a_kind_and_the_tally_counts_them():
    src, tgt, T_gt, info = _pair(np.random.default_rng(1), noise=50.0)  # descriptors of pure noise
    res = diagnose_pair(src, tgt, T_gt, info, 300, CFG, pair_seed(0, "scene", 0, 2, 300))
    tally = Tally()
    for ok, kind in res.values():
        assert not ok and kind in ("ranking", "search")
        tally.add(ok, kind)
    tally.add(True, None)
    assert (tally.pairs, tally.registered, sum(tally.kinds.values())) == (3, 1, 2)
    assert tally.row("3DMatch", "overlap").split()[:4] == ["3DMatch", "overlap", "3", "33.3"]


def test_bad_input_is_one_line_naming_the_setting(tmp_path):
    import subprocess
    import sys

    ckpt = tmp_path / "model.ckpt"
    for args, words in (([str(ckpt)], "checkpoint not found"),
                        ([str(ckpt), "--pairs", "0"], "--pairs must be >= 1"),
                        ([__file__, "--root", str(tmp_path)], f"no benchmark folder {tmp_path}/benchmarks/3DMatch")):
        proc = subprocess.run([sys.executable, "-m", "pcrcg.benchmarks.ranking", *args], capture_output=True, text=True)
        assert proc.returncode == 2
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("python -m pcrcg.benchmarks.ranking: error: ") and words in last
