"""Data-set statistics (pcrcg.data.stats): each measure on tiny data made here, the CLI end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pcrcg.data.stats import measures as M
from pcrcg.data.stats import collect as C

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_FRAGMENTS = SHARED / "real-3dmatch-fragments" / "7-scenes-redkitchen"


# --------------------------------------------------------------------------- shapes made here


def _grid(a: float, b: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(0, a + 1e-9, step), np.arange(0, b + 1e-9, step), indexing="ij")
    return u.ravel(), v.ravel()


def room_of_four_planes(step: float = 0.03) -> np.ndarray:
    """Floor (z = 0) and three walls (x = 0, x = 3, y = 0) of a 3 x 2.5 x 2 m room: (N, 3)."""
    u, v = _grid(3.0, 2.5, step)
    floor = np.stack([u, v, 0 * u], 1)
    w, h = _grid(2.5, 2.0, step)
    left = np.stack([0 * w, w, h], 1)
    right = np.stack([0 * w + 3.0, w, h], 1)
    x, h = _grid(3.0, 2.0, step)
    back = np.stack([x, 0 * x, h], 1)
    return np.concatenate([floor, left, right, back])


def sphere(n: int = 20000, radius: float = 1.0, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def cube_surface(side: float = 2.0, step: float = 0.02) -> np.ndarray:
    u, v = _grid(side, side, step)
    faces = []
    for axis in range(3):
        for c in (0.0, side):
            p = np.zeros((len(u), 3))
            others = [k for k in range(3) if k != axis]
            p[:, axis], p[:, others[0]], p[:, others[1]] = c, u, v
            faces.append(p)
    return np.concatenate(faces)


# --------------------------------------------------------------------------- sizes


def test_count_voxels_on_a_known_lattice():
    # 20 x 10 x 4 voxel centres 2.5 cm apart, each with 5 copies jittered by up to 4 mm: 800 occupied
    # voxels (Open3D anchors its grid at the points' minimum, so clusters must stay clear of the edges)
    rng = np.random.default_rng(0)
    idx = np.stack(np.meshgrid(np.arange(20), np.arange(10), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    centres = (idx + 0.5) * 0.025
    pts = np.repeat(centres, 5, 0) + rng.uniform(-0.004, 0.004, size=(len(centres) * 5, 3))
    assert M.count_voxels(pts, 0.025) == 800
    assert len(M.voxel_downsample(pts, 0)) == len(pts)


def test_extent_of_a_rotated_box():
    rng = np.random.default_rng(1)
    box = rng.uniform(0, 1, size=(40000, 3)) * [4.0, 2.0, 1.0]
    np.testing.assert_allclose(M.extent_sides(box, pca=False, trim=0), [4, 2, 1], atol=0.01)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotated = box @ q.T + [5.0, -3.0, 2.0]
    np.testing.assert_allclose(M.extent_sides(rotated, trim=0), [4, 2, 1], atol=0.02)
    # the default trims 2% at each end: 96% of each side
    np.testing.assert_allclose(M.extent_sides(rotated), [3.84, 1.92, 0.96], atol=0.03)
    # a few stray points move the full box but not the trimmed one
    stray = np.concatenate([box, [[30.0, 0, 0], [-30.0, 0, 0]]])
    assert M.extent_sides(stray, pca=False, trim=0)[0] > 50
    assert M.extent_sides(stray, pca=False)[0] == pytest.approx(3.84, abs=0.03)


# --------------------------------------------------------------------------- planes


def test_planarity_of_a_room_is_one_and_of_a_sphere_low():
    room = room_of_four_planes()
    p = M.planarity(room)
    assert p > 0.97
    assert M.planarity(room) == p  # seeded: the same every time
    assert M.planarity(sphere()) < 0.2
    # one plane fills one of the four: all its points
    u, v = _grid(2.0, 2.0, 0.02)
    assert M.planarity(np.stack([u, v, 0 * u], 1)) == pytest.approx(1.0)
    assert math.isnan(M.planarity(np.zeros((0, 3))))


def test_planarity_counts_only_n_planes():
    room = room_of_four_planes()
    assert 0.2 < M.planarity(room, n_planes=1) < 0.4  # the floor is ~7.5 of ~23.5 m2
    assert M.planarity(room, n_planes=2) < M.planarity(room, n_planes=3) < M.planarity(room, n_planes=4)


# --------------------------------------------------------------------------- normals


def test_axial_cells_are_sign_free_and_nearly_equal_area():
    rng = np.random.default_rng(2)
    v = rng.normal(size=(60000, 3))
    c = M.axial_cells(v)
    np.testing.assert_array_equal(c, M.axial_cells(-v))
    counts = np.bincount(c, minlength=200)
    # nearly equal areas: within about +-25% of the mean (the extremes sit at the equator seam)
    assert counts.min() > 0.65 * counts.mean() and counts.max() < 1.4 * counts.mean()
    assert M.orientation_entropy(v) == pytest.approx(M.max_orientation_entropy(), abs=0.03)
    assert M.max_orientation_entropy() == pytest.approx(math.log2(200))


def test_orientation_entropy_of_plane_cube_and_sphere():
    u, v = _grid(2.0, 2.0, 0.05)
    plane = np.stack([u, v, 0 * u], 1)
    assert M.normal_entropy(plane, voxel=0) == pytest.approx(0.0, abs=1e-9)
    # a cube's six faces have three axial orientations of equal areas: log2(3) bits
    faces = np.repeat(np.concatenate([np.eye(3), -np.eye(3)]), 100, 0)
    assert M.orientation_entropy(faces) == pytest.approx(math.log2(3))
    # estimated at 5 cm voxels the cube's edges add blended normals; a sphere spreads over every cell
    cube = M.normal_entropy(cube_surface(), voxel=0.05)
    assert math.log2(3) - 0.05 < cube < 3.5
    assert M.normal_entropy(sphere(), voxel=0.05) > 7.0
    n = M.estimate_normals(plane, 0.1)
    assert n.shape == plane.shape
    np.testing.assert_allclose(np.abs(n[:, 2]), 1.0, atol=1e-6)
    assert math.isnan(M.orientation_entropy(np.zeros((4, 3))))


# --------------------------------------------------------------------------- pairs, frames, summaries


def test_overlap_histogram_and_hole_rate_and_summary():
    counts = M.overlap_histogram([0.05, 0.15, 0.15, 0.95, 1.0, float("nan")])
    assert counts == [1, 2, 0, 0, 0, 0, 0, 0, 0, 2]
    depth = np.ones((4, 8), np.float32)
    depth[:1] = 0
    assert M.hole_rate(depth) == 0.25
    assert M.hole_rate(np.zeros((2, 2), np.uint16)) == 1.0
    depth[1:, :5] = 2.0  # 15 pixels at 2 m, 9 at 1 m, 8 holes: the median of what has depth is 2 m
    assert M.median_depth(depth) == 2.0
    depth[1:, :3] = np.nan  # 6 at 2 m, 9 at 1 m left: 1 m
    assert M.median_depth(depth) == 1.0
    assert np.isnan(M.median_depth(np.zeros((2, 2), np.float32)))


def test_covisibility_of_two_views_of_a_wall():
    """A wall 2 m ahead: the same view sees all of it, a view shifted by half the wall's width in
    the image sees half, a view turned round none, a wall moved 0.5 m away none (depth disagrees)."""
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 2.0, np.float32)
    eye = np.eye(4)
    assert M.covisibility(depth, eye, depth, eye, K) == 1.0
    shifted = np.eye(4)
    shifted[0, 3] = 32 * 2.0 / 50.0  # half the image width at 2 m
    assert M.covisibility(depth, eye, depth, shifted, K) == pytest.approx(0.5, abs=0.04)
    turned = np.diag([-1.0, 1.0, -1.0, 1.0])
    assert M.covisibility(depth, eye, depth, turned, K) == 0.0
    assert M.covisibility(depth, eye, depth + 0.5, eye, K) == 0.0
    assert np.isnan(M.covisibility(np.zeros_like(depth), eye, depth, eye, K))
    bins = C.matches_by_covisibility([0.05, 0.4, 0.45, 1.0, float("nan")], [0, 3, 5, 20, 7])
    assert [(b["n"], b["mean"]) for b in bins] == [(1, 0.0), (2, 4.0), (1, 20.0)]
    assert bins[0]["verified_share"] == 0.0 and bins[1]["verified_share"] == 1.0
    per = C.matches_by_benchmark(["3DMatch", "3DLoMatch", "3DMatch", "3DMatch"], [10, 0, 0, 20])
    assert (per["3DMatch"]["n"], per["3DMatch"]["mean"]) == (3, 10.0) and per["3DLoMatch"]["mean"] == 0.0
    assert per["3DMatch"]["verified_share"] == pytest.approx(2 / 3) and per["3DLoMatch"]["verified_share"] == 0.0
    assert list(C.matches_by_benchmark(["3DLoMatch"], [4])) == ["3DLoMatch"]
    with pytest.raises(ValueError, match="2 benchmarks for 1 view pairs"):
        C.matches_by_benchmark(["3DMatch", "3DMatch"], [1])
    s = M.summarize([1, 2, 3, 4, float("nan"), None])
    assert s["n"] == 4 and s["mean"] == 2.5 and s["min"] == 1 and s["max"] == 4
    assert M.summarize([])["mean"] is None
    assert M.entropy_bits([1, 1, 1, 1]) == pytest.approx(2.0)


# --------------------------------------------------------------------------- CLI


def _run(argv, capsys):
    from pcrcg.data.stats.cli import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code, capsys.readouterr()


def test_pair_motion_is_the_angle_and_distance_between_the_first_cameras():
    from pcrcg.data.layout import PairRecord
    from pcrcg.data.stats.collect import pair_motion
    from pcrcg.geometry import make_transform

    def rz(deg):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])

    pairs = [PairRecord("s", 0, k + 2, make_transform(rz(a), [d, 0, 0]), 0.2, 10)
             for k, (a, d) in enumerate([(30, 0.5), (60, 1.0), (90, 2.0)])]
    m = pair_motion(pairs)
    assert m["rotation_deg"]["median"] == pytest.approx(60) and m["rotation_deg"]["max"] == pytest.approx(90)
    assert m["translation_m"]["median"] == pytest.approx(1.0) and m["translation_m"]["min"] == pytest.approx(0.5)


def test_bad_root_is_one_line_error_naming_it(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    code, io = _run([str(missing), "--out", str(tmp_path / "s")], capsys)
    assert code == 2
    lines = io.err.strip().splitlines()
    assert len(lines) == 1 and str(missing) in lines[0] and "does not exist" in lines[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    code, io = _run([str(empty), "--out", str(tmp_path / "s")], capsys)
    assert code == 2 and str(empty) in io.err and "3DMatch layout" in io.err
    code, io = _run(["--fragments-dir", str(empty), "--out", str(tmp_path / "s")], capsys)
    assert code == 2 and str(empty) in io.err
    assert not (tmp_path / "s.md").exists()


def test_cli_end_to_end_on_tiny(tiny_root, tmp_path, capsys):
    from pcrcg.data.stats.cli import main

    out = tmp_path / "reports" / "stats"
    main([str(tiny_root), "--out", str(out), "--pairs", "2", "--fragments", "6", "--frames", "12",
          "--profile", "tiny", "--quiet"])
    printed = capsys.readouterr().out
    assert "| measure | synthmatch-tiny |" in printed
    md = Path(f"{out}.md").read_text()
    assert "planarity" in md and "FPFH + RANSAC RR, 3DLoMatch" in md
    data = json.loads(Path(f"{out}.json").read_text())
    col = data["columns"][0]
    fr = col["fragments"]
    n_frag = len(list((tiny_root / "fragments").glob("*/cloud_bin_*.ply")))
    assert fr["count"] == n_frag and fr["measured"] == min(6, n_frag)
    assert 1000 < fr["points"]["mean"] < 50000
    assert 0.3 < fr["planarity"]["median"] <= 1.0
    assert 0 < fr["normal_entropy"]["median"] < math.log2(200)
    assert len(fr["extent_pca_median"]) == 3 and fr["extent_pca_median"][0] >= fr["extent_pca_median"][2]
    for b in ("3DMatch", "3DLoMatch"):
        f = col["fpfh"][b]
        assert f["pairs"] == min(2, f["listed"]) and f["counted"] <= f["pairs"]
        assert sum(col["overlap"][b]["counts"]) == col["overlap"][b]["n_with_overlap"] > 0
        assert col["overlap"][b]["rotation_deg"]["n"] == col["overlap"][b]["n"]
    assert "relative rotation" in md and "inlier ratio" in md
    assert sum(col["overlap"]["train"]["counts"]) > 0
    run = sum(col["fpfh"][b]["pairs"] for b in ("3DMatch", "3DLoMatch"))
    assert col["sift"]["view_pairs"] == 2 * run  # first-first and last-last of each pair run
    assert col["sift"]["grid"]["size"] == "160x120"
    assert col["sift"]["grid"]["keypoints"]["mean"] > 0
    assert col["sift"]["covisibility"]["n"] == col["sift"]["view_pairs"]  # every view pair has depth and pose
    assert sum(b["n"] for b in col["sift"]["grid_by_covisibility"]) == col["sift"]["view_pairs"]
    per = col["sift"]["grid_by_benchmark"]
    assert {b: per[b]["n"] for b in per} == {b: 2 * col["fpfh"][b]["pairs"] for b in per}
    assert "of 3DMatch / 3DLoMatch pairs" in md
    assert "co-visibility" in md
    assert 0 <= col["depth"]["mean"] < 1 and col["depth"]["frames"] == 12
    assert col["depth"]["median_m"]["n"] == 12 and 0.4 < col["depth"]["median_m"]["median"] < 4.5
    assert data["settings"]["pairs"] == 2
    flat = col["summary"]
    samp = col["sampling"]
    assert samp["voxel"] == pytest.approx(0.06) and samp["n_points"] == [5000, 2500, 1000, 500, 250]
    for b in ("3DMatch", "3DLoMatch"):
        below = [samp[b]["below"][str(n)] for n in samp["n_points"]]
        assert samp[b]["pairs"] == col["overlap"][b]["n"] and below == sorted(below, reverse=True)
        assert flat[f"{b}_below_5000"] == samp[b]["below"]["5000"]
    assert "fewer than N points at the profile's model voxel" in md and "5000: " in md
    assert flat["planarity_median"] == fr["planarity"]["median"] and flat["fragments"] == n_frag
    assert flat["3DMatch_fpfh_counted"] == col["fpfh"]["3DMatch"]["counted"]
    assert Path(f"{out}.png").stat().st_size > 10000


@pytest.mark.shared
def test_real_fragments_folder_matches_the_measured_reference(tmp_path, capsys):
    """Real 3DMatch fragments (7-scenes-redkitchen 0-5): ~19k points at 2.5 cm, planarity ~0.55,
    about 2.4 x 1.8 x 1.9 m; no frames given: image rows are dashes."""
    if not REAL_FRAGMENTS.is_dir():
        pytest.skip(f"{REAL_FRAGMENTS} is absent")
    from pcrcg.data.stats.cli import main

    out = tmp_path / "real"
    main(["--fragments-dir", str(REAL_FRAGMENTS), "--out", str(out), "--no-fpfh", "--no-picture", "--quiet"])
    printed = capsys.readouterr().out
    col = json.loads(Path(f"{out}.json").read_text())["columns"][0]
    fr = col["fragments"]
    assert fr["count"] == 6
    assert 15000 < fr["points"]["mean"] < 21000
    assert 0.45 < fr["planarity"]["median"] < 0.65
    np.testing.assert_allclose(fr["extent_xyz_median"], [2.4, 1.8, 1.9], atol=0.2)
    assert col["sift"] is None and col["depth"] is None and col["fpfh"] is None
    row = next(ln for ln in printed.splitlines() if ln.startswith("| depth holes"))
    assert row.rstrip().endswith("| – |")


@pytest.mark.slow
@pytest.mark.shared
def test_real_folder_with_frames_and_benchmarks(tmp_path, capsys):
    """Every row on real data: the release's fragments 0-5, their frames (3DMatch's 50-frame rule
    where a fragment has no .info.txt) and the official benchmark files."""
    frames = SHARED / "real-rgbd" / "7-scenes-redkitchen" / "seq-01"
    bench = SHARED / "3dmatch-benchmarks"
    for p in (REAL_FRAGMENTS, frames, bench):
        if not p.is_dir():
            pytest.skip(f"{p} is absent")
    from pcrcg.data.stats.cli import main

    out = tmp_path / "real"
    main(["--fragments-dir", str(REAL_FRAGMENTS), "--frames-dir", str(frames), "--benchmarks-dir", str(bench),
          "--frames-per-fragment", "50", "--pairs", "4", "--frames", "20", "--name", "real", "--out", str(out),
          "--quiet"])
    col = json.loads(Path(f"{out}.json").read_text())["columns"][0]
    assert col["name"] == "real"
    assert col["fpfh"]["3DMatch"]["available"] == 13 and col["fpfh"]["3DMatch"]["pairs"] == 4
    assert col["fpfh"]["3DLoMatch"]["available"] == 1
    assert col["overlap"]["3DMatch"]["n"] > 100  # every pair of the scene's gt.log
    assert col["sift"]["view_pairs"] == 10 and col["sift"]["native_size"] == ["640x480"]
    assert col["sift"]["native"]["keypoints"]["mean"] > col["sift"]["grid"]["keypoints"]["mean"]
    assert 0.02 < col["depth"]["mean"] < 0.3
    assert 1.2 < col["depth"]["median_m"]["median"] < 2.6  # 7-Scenes' kitchen: 1.4-2.4 m per frame
    assert 0.0 < col["sift"]["covisibility"]["median"] < 1.0


def test_below_n_is_the_share_of_pairs_under_each_sample_size():
    from pcrcg.data.stats.collect import below_n

    assert below_n(np.array([900, 2000, 3000, 6000]), [5000, 2500, 1000, 250]) == {
        5000: 0.75, 2500: 0.5, 1000: 0.25, 250: 0.0}
    assert below_n(np.array([], dtype=np.int64), [5000]) == {}
