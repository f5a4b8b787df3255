"""The 3DMatch protocol on hand-made cases (pcrcg.evaluation.metrics)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pcrcg.data.layout import PairRecord, read_gt_log, write_gt_info, write_gt_log
from pcrcg.errors import DataError
from pcrcg.evaluation.metrics import (
    SceneGT,
    correspondence_metrics,
    counted_mask,
    feature_match_recall,
    information_matrix,
    inlier_ratio,
    load_benchmark,
    read_estimates,
    registration_error,
    rotation_error_deg,
    rotation_to_quaternion,
    score_benchmark,
    score_directories,
    score_scene,
    transformation_error,
    translation_error,
    write_estimates,
)
from pcrcg.geometry import axis_angle_to_matrix, invert, make_transform, random_rotation


def _scene(rng, pairs, scene="s", n_frag=10, n_pts=500):
    """A SceneGT with random rigid ground truths and info matrices of random point sets."""
    recs, infos = [], []
    for i, j in pairs:
        T = make_transform(random_rotation(rng), rng.normal(size=3))
        recs.append(PairRecord(scene, i, j, T, n_fragments=n_frag))
        infos.append(information_matrix(rng.normal(scale=1.0, size=(n_pts, 3)) + rng.normal(size=3)))
    return SceneGT(scene, tuple(recs), np.stack([r.transform for r in recs]), np.stack(infos))


def _perturb(T_gt, t=np.zeros(3), axis=(0, 0, 1), angle=0.0):
    """T_gt @ D with D a known residual motion (rotation about ``axis`` by ``angle``, then ``t``)."""
    return T_gt @ make_transform(axis_angle_to_matrix(np.asarray(axis, float), angle), np.asarray(t, float))


# --------------------------------------------------------------------------- per pair


def test_quaternion_matches_scipy_and_has_nonnegative_w():
    R = Rotation.random(500, random_state=3).as_matrix()
    R = np.concatenate([R, np.eye(3)[None], axis_angle_to_matrix([1, 0, 0], np.pi)[None]])
    q = rotation_to_quaternion(R)
    ref = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    ref[ref[:, 0] < 0] *= -1
    assert np.all(q[:, 0] >= 0)
    # a 180-degree rotation has w = 0 and q ~ -q: compare up to sign there
    same = np.minimum(np.abs(q - ref).max(1), np.abs(q + ref).max(1))
    assert same.max() < 1e-12


def test_transformation_error_of_pure_translation_is_its_squared_norm():
    info = information_matrix(np.random.default_rng(0).normal(size=(300, 3)))
    delta = make_transform(np.eye(3), [0.1, -0.2, 0.05])
    # e = [t, 0]: e^T info e / n = |t|^2 because the translation block is n * I
    assert transformation_error(delta, info) == pytest.approx(0.1**2 + 0.2**2 + 0.05**2, rel=1e-12)


def test_transformation_error_of_rotation_uses_half_angle_quaternion():
    # one point at distance r from the axis: e^T info e / n = r^2 * sin(a/2)^2 (vector part of q)
    p = np.array([[0.0, 2.0, 0.0]])
    info = information_matrix(p)
    a = 0.3
    delta = make_transform(axis_angle_to_matrix([0, 0, 1], a), np.zeros(3))
    assert transformation_error(delta, info) == pytest.approx((2.0 * np.sin(a / 2)) ** 2, rel=1e-12)


def test_ground_truth_as_estimate_has_zero_error():
    rng = np.random.default_rng(1)
    g = _scene(rng, [(0, 2), (1, 5)])
    assert np.allclose(registration_error(g.transforms, g.transforms, g.infos), 0.0, atol=1e-20)


def test_known_perturbations_pass_or_fail_exactly_as_the_formula_says():
    rng = np.random.default_rng(2)
    pairs = [(0, k) for k in range(2, 42)]
    g = _scene(rng, pairs)
    est, expected = {}, []
    for k, p in enumerate(g.pairs):
        n = g.infos[k][0, 0]
        # a translation of length L has error L^2 exactly: aim just below / above the threshold
        target = 0.2 * (0.95 if k % 2 == 0 else 1.05)
        axis = rng.normal(size=3)
        delta_t = axis / np.linalg.norm(axis) * target
        if k % 4 >= 2:  # add a rotation, then compute the exact error with the formula by hand
            D = make_transform(axis_angle_to_matrix(rng.normal(size=3), rng.uniform(0.01, 0.2)), delta_t)
            q = Rotation.from_matrix(D[:3, :3]).as_quat()
            q = q if q[3] >= 0 else -q
            e = np.concatenate([D[:3, 3], q[:3]])
            err = e @ g.infos[k] @ e / n
        else:
            D = make_transform(np.eye(3), delta_t)
            err = target**2
        est[(p.i, p.j)] = p.transform @ D
        expected.append(err <= 0.04)
    sc = score_scene(g, est)
    assert sc.success.tolist() == expected
    assert np.allclose(sc.error[::4], (0.2 * 0.95) ** 2) and np.allclose(sc.error[1::4], (0.2 * 1.05) ** 2)
    assert 0 < sum(expected) < len(expected)


def test_inlier_ratio_hand_made():
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    T = make_transform(axis_angle_to_matrix([0, 0, 1], np.pi / 2), [1.0, 2.0, 3.0])
    tgt = src @ T[:3, :3].T + T[:3, 3]
    tgt[1] += [0.099, 0, 0]  # inlier (residual < 10 cm)
    tgt[2] += [0, 0.101, 0]  # outlier
    tgt[3] += [5.0, 0, 0]  # outlier
    assert inlier_ratio(src, tgt, T) == pytest.approx(0.5)
    assert inlier_ratio(np.zeros((0, 3)), np.zeros((0, 3)), T) == 0.0


def test_feature_match_recall_uses_strict_five_percent():
    assert feature_match_recall([0.05, 0.0501, 0.5, 0.0]) == pytest.approx(0.5)
    m = correspondence_metrics({"a": [0.1, 0.0], "b": [0.2, 0.2, 0.2, 0.01]})
    assert m["ir"] == pytest.approx(100 * np.mean([0.05, 0.1525]))  # averaged per scene then over scenes
    assert m["fmr"] == pytest.approx(100 * np.mean([0.5, 0.75]))
    assert m["fmr_pair"] == pytest.approx(100 * 4 / 6)


def test_rre_rte():
    R1 = axis_angle_to_matrix([0, 1, 0], np.radians(30))
    assert rotation_error_deg(R1, np.eye(3)) == pytest.approx(30.0)
    assert translation_error(np.array([1.0, 2, 2]), np.zeros(3)) == pytest.approx(3.0)


def test_information_matrix_matches_open3d():
    import open3d as o3d

    p = np.random.default_rng(0).normal(size=(200, 3)) + [1, 2, 3]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    G = o3d.pipelines.registration.get_information_matrix_from_point_clouds(pcd, pcd, 0.01, np.eye(4))
    perm = [3, 4, 5, 0, 1, 2]  # Open3D puts rotation first
    assert np.allclose(np.asarray(G)[np.ix_(perm, perm)], information_matrix(p), atol=1e-8)


# --------------------------------------------------------------------------- recall


def test_ground_truth_gives_full_recall_and_adjacent_pairs_do_not_count():
    rng = np.random.default_rng(4)
    g = _scene(rng, [(0, 1), (0, 2), (1, 2), (1, 3), (2, 3)])
    assert counted_mask(g.pairs).tolist() == [False, True, False, True, False]
    est = dict(zip(g.keys(), g.transforms))
    assert score_scene(g, est).recall == 100.0
    # adjacent pairs may be anything: recall is unchanged
    bad = {k: (np.eye(4) if k[1] == k[0] + 1 else T) for k, T in est.items()}
    sc = score_scene(g, bad)
    assert sc.recall == 100.0 and sc.n_counted == 2
    # a non-adjacent failure halves it; a missing estimate is a failure too
    del bad[(0, 2)]
    assert score_scene(g, bad).recall == 50.0


def test_recall_is_averaged_per_scene_then_over_scenes():
    rng = np.random.default_rng(5)
    a = _scene(rng, [(0, 2), (0, 3), (0, 4), (0, 5)], "a")
    b = _scene(rng, [(0, 2)], "b")
    est = {"a": {(0, 2): a.transforms[0]}, "b": {(0, 2): b.transforms[0]}}  # a: 1/4, b: 1/1
    s = score_benchmark({"a": a, "b": b}, est)
    assert s.scenes == {"a": 25.0, "b": 100.0}
    assert s.rr == pytest.approx(62.5) and s.rr_pair == pytest.approx(40.0)
    assert s.n_missing == 3


def test_predator_variant_never_counts_the_first_pair():
    rng = np.random.default_rng(6)
    g = _scene(rng, [(0, 3), (0, 5), (1, 4), (2, 3)])  # first pair non-adjacent
    est = dict(zip(g.keys(), g.transforms))
    est[(0, 5)] = np.eye(4) @ make_transform(np.eye(3), [9, 9, 9])  # one failure
    official = score_scene(g, est)
    variant = score_scene(g, est, predator_variant=True)
    assert official.n_counted == 3 and official.recall == pytest.approx(200 / 3)
    assert variant.n_counted == 2 and variant.recall == pytest.approx(50.0)
    # when the first pair fails instead, only the official protocol sees it
    est2 = dict(zip(g.keys(), g.transforms))
    est2[(0, 3)] = make_transform(np.eye(3), [1, 0, 0])
    assert score_scene(g, est2).recall == pytest.approx(200 / 3)
    assert score_scene(g, est2, predator_variant=True).recall == 100.0


def test_rre_rte_over_registered_pairs_median_per_scene():
    rng = np.random.default_rng(7)
    g = _scene(rng, [(0, 2), (0, 3), (0, 4), (1, 2)])
    est = {
        (0, 2): _perturb(g.transforms[0], t=[0.01, 0, 0]),
        (0, 3): _perturb(g.transforms[1], t=[0.03, 0, 0]),
        (0, 4): _perturb(g.transforms[2], t=[5.0, 0, 0]),  # fails: not in RRE/RTE
        (1, 2): _perturb(g.transforms[3], t=[0.07, 0, 0]),  # adjacent: not counted
    }
    s = score_benchmark({"s": g}, {"s": est})
    # RTE of T_gt @ D vs T_gt is |R_gt t_D| = |t_D|
    assert s.rte == pytest.approx(0.02) and s.rte_pair_mean == pytest.approx(0.02)
    assert s.rre == pytest.approx(0.0, abs=1e-6)


def test_zero_information_matrix_always_fails():
    rng = np.random.default_rng(8)
    g = _scene(rng, [(0, 2), (0, 3)])
    infos = g.infos.copy()
    infos[1] = 0.0
    g0 = SceneGT(g.scene, g.pairs, g.transforms, infos)
    sc = score_scene(g0, dict(zip(g0.keys(), g0.transforms)))
    assert sc.success.tolist() == [True, False] and sc.recall == 50.0


# --------------------------------------------------------------------------- files


def _write_benchmark(root, rng, scenes):
    for name, pairs in scenes.items():
        g = _scene(rng, pairs, name)
        d = root / name
        d.mkdir(parents=True)
        write_gt_log(d / "gt.log", list(g.pairs))
        write_gt_info(d / "gt.info", list(g.pairs), list(g.infos))
    return load_benchmark(root)


def test_est_log_round_trip_and_directory_scoring(tmp_path):
    rng = np.random.default_rng(9)
    gt = _write_benchmark(tmp_path / "bench", rng, {"a": [(0, 2), (1, 3), (0, 1)], "b": [(2, 4)]})
    est = {s: {k: _perturb(T, t=[0.01, 0.02, 0.0], axis=rng.normal(size=3), angle=0.01)
               for k, T in zip(g.keys(), g.transforms)} for s, g in gt.items()}
    for s, g in gt.items():
        write_estimates(tmp_path / "est" / s / "est.log", g, est[s])
    back = read_estimates(tmp_path / "est" / "a" / "est.log")
    assert set(back) == set(est["a"])
    for k in back:
        assert np.allclose(back[k], est["a"][k], atol=1e-9)
    recs = read_gt_log(tmp_path / "est" / "a" / "est.log")
    assert [(r.i, r.j, r.n_fragments) for r in recs] == [(p.i, p.j, p.n_fragments) for p in gt["a"].pairs]
    s = score_directories(tmp_path / "bench", tmp_path / "est")
    assert s.rr == 100.0 and s.n_counted == 3
    # a missing scene counts as failures
    (tmp_path / "est" / "b" / "est.log").unlink()
    s = score_directories(tmp_path / "bench", tmp_path / "est")
    assert s.scenes["b"] == 0.0 and s.missing_scenes == ["b"] and s.rr == 50.0


def test_bad_inputs_name_the_file(tmp_path):
    rng = np.random.default_rng(10)
    _write_benchmark(tmp_path / "bench", rng, {"a": [(0, 2)]})
    with pytest.raises(DataError, match="nope"):
        score_directories(tmp_path / "nope", tmp_path)
    with pytest.raises(DataError, match="est"):
        score_directories(tmp_path / "bench", tmp_path / "est")  # estimate folder missing
    (tmp_path / "bench" / "a" / "gt.info").unlink()
    with pytest.raises(DataError, match=r"gt\.info"):
        load_benchmark(tmp_path / "bench")
    bad = tmp_path / "est.log"
    bad.write_text("0 2 10\n1 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DataError, match=str(bad)):
        read_estimates(bad)
    bad.write_text("0 2 10\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DataError, match="not rigid"):
        read_estimates(bad)
    T = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
    bad.write_text(f"0 2 10\n{T}0 2 10\n{T}")
    with pytest.raises(DataError, match="two estimates"):
        read_estimates(bad)


def test_invert_is_consistent_with_error_definition():
    # the error of T_gt @ D is the error of D alone: inv(T_gt) @ T_est = D
    rng = np.random.default_rng(11)
    T = make_transform(random_rotation(rng), rng.normal(size=3))
    D = make_transform(axis_angle_to_matrix([1, 1, 0], 0.05), [0.02, 0, 0.01])
    info = information_matrix(rng.normal(size=(50, 3)))
    assert registration_error(T @ D, T, info) == pytest.approx(transformation_error(D, info), rel=1e-9)
    assert np.allclose(invert(T) @ T, np.eye(4))
