"""color_coverage sweeps (views, windows), the coverage figure and the benchmark module."""

from __future__ import annotations

import numpy as np
import pytest

from pcrcg.lifting.coverage import check_growth, coverage_sweep, format_rows, load_samples, main, overlap_coloring
from pcrcg.vision.matching import MatchCache


@pytest.fixture(scope="module")
def samples():
    return load_samples(None, "val", 2)  # two toy pairs


def test_sweep_grows_as_in_the_paper(samples, tmp_path_factory):
    cache = MatchCache(tmp_path_factory.mktemp("m"))
    rows = coverage_sweep(samples, cache=cache)
    checks = check_growth(rows)
    assert len(checks) == 3 and all(checks.values()), format_rows(rows)
    by = {(r.sweep, r.projection, r.views, r.window_size): r.color_coverage for r in rows}
    # implicit: one view leaves roughly a third uncovered, two views cover nearly all (paper, Fig. 3)
    assert 0.55 < by[("views", "implicit", 1, 11)] < 0.8
    assert by[("views", "implicit", 2, 11)] > 0.95
    # explicit covers only the matched regions: well below implicit, growing with the window
    assert by[("window", "explicit", 2, 3)] < 0.1 < by[("window", "explicit", 2, 17)] < by[("views", "implicit", 2, 11)]
    assert cache.misses == 6  # 3 view pairs x 2 samples, computed once for all 10 settings


def test_overlap_coloring_on_known_geometry():
    # src: 4 points on a line; the pose moves them 1 m along x onto the target's first 3 (the 4th has none
    # within the radius); target point 3 lies far away
    src = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [5.0, 0, 0]])
    tgt = np.array([[1.0, 0, 0], [1.1, 0, 0], [1.2, 0, 0], [9.0, 0, 0]])
    T = np.eye(4)
    T[0, 3] = 1.0
    # overlap = src 0..2 <-> tgt 0..2: colored both (0), src only (1), neither (2); src 3 is not in the overlap
    both, one = overlap_coloring(np.array([1, 1, 0, 1], bool), np.array([1, 0, 0, 1], bool), src, tgt, T, 0.03)
    assert (both, one) == pytest.approx((1 / 3, 1 / 3))
    # target only colored: also one side
    assert overlap_coloring(np.zeros(4, bool), np.ones(4, bool), src, tgt, T, 0.03) == pytest.approx((0.0, 1.0))
    # the identity leaves no source point near the target: no overlap to color
    assert overlap_coloring(np.ones(4, bool), np.ones(4, bool), src, tgt, np.eye(4), 0.03) is None


def test_sweep_reports_how_the_overlap_is_colored(samples):
    rows = coverage_sweep(samples, views=(1, 2), windows=(11,))
    by = {(r.sweep, r.projection, r.views): r for r in rows}
    one, two = by[("views", "implicit", 1)], by[("views", "implicit", 2)]
    for r in rows:
        assert 0.0 <= r.overlap_both and 0.0 <= r.overlap_one_side and r.overlap_both + r.overlap_one_side <= 1.0
    # one view per fragment colors less of the shared surface on both sides than two
    assert one.overlap_both < two.overlap_both
    assert "overlap: both" in format_rows(rows)


def test_check_growth_detects_violations():
    from pcrcg.lifting.coverage import CoverageRow

    rows = [CoverageRow("views", "implicit", v, 11, c, 1) for v, c in ((1, 0.5), (2, 0.5), (3, 0.6))]
    rows += [CoverageRow("window", "explicit", 2, w, c, 1) for w, c in ((3, 0.1), (7, 0.2), (11, 0.2))]
    checks = check_growth(rows)
    assert checks == {"implicit: views 1 < 2 <= 3": False, "explicit: windows 3 < 7 < 11": False}


def test_cli_on_toy_data(capsys):
    rows = main(["n_pairs=1", "windows=[3,17]", "views=[1,2]"])
    out = capsys.readouterr().out
    assert "color_coverage" in out and "toy scene" in out
    assert len(rows) == 2 * 2 + 2


def test_coverage_figure(tmp_path):
    import matplotlib.image as mpimg

    from pcrcg.plots.coverage import main as plot_main

    out = plot_main([f"out={tmp_path / 'cov.png'}", "pair=1"])
    img = mpimg.imread(out)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 3 * img.shape[0] // 2
    # three panels with black (uncovered) points in the first one
    assert (img[..., :3].sum(axis=2) < 0.05).mean() > 0.01


def test_coverage_masks_nest(samples):
    from pcrcg.plots.coverage import coverage_masks

    m = coverage_masks(samples[0], "src", "implicit")
    assert set(m) == {1, 2, 3}
    assert np.all(m[2][m[1]]) and np.all(m[3][m[2]])  # more views never remove coverage
    assert m[1].mean() < m[2].mean()


def test_benchmark_smoke(capsys):
    from pcrcg.benchmarks.vision import main as bench

    rows = bench(["reps=1", "points=[500]", "archs=[resnet18]", "sizes=[[32,40]]", "skip=[matcher]"])
    parts = {r["part"] for r in rows}
    assert parts == {"lifting", "encoder"}
    assert all(r["s_per_pair"] > 0 for r in rows)
    assert "encoder forward+backward" in capsys.readouterr().out
