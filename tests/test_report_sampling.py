"""pcrcg.report.sampling: recall per N split by how the protocol drew each pair's N points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pcrcg.data.layout import Layout, write_ply
from pcrcg.data.stats.collect import model_points
from pcrcg.evaluation.pairs import PAIR_COLUMNS
from pcrcg.report.sampling import COLUMNS, format_table, main, pair_regimes, regime_table

VOXEL = 0.1


def test_a_pair_is_sampled_by_scores_only_where_both_fragments_have_more_than_n_points():
    src, tgt = np.array([100, 100, 40, 50, 30]), np.array([100, 50, 100, 50, 20])
    assert pair_regimes(src, tgt, 50).tolist() == ["scores", "mixed", "mixed", "uniform", "uniform"]
    assert pair_regimes(src, tgt, 10).tolist() == ["scores"] * 5
    with pytest.raises(ValueError, match="differ in length"):
        pair_regimes(src, tgt[:2], 50)


def _pairs(rows: list[tuple[str, int, int, int, int, int]]) -> pd.DataFrame:
    """(scene, i, j, N, counted, registered) rows in the evaluation's per-pair format."""
    return pd.DataFrame([{"scene": s, "i": i, "j": j, "n_points": n, "counted": c, "present": 1, "registered": r,
                          "error": np.nan, "rre": np.nan, "rte": np.nan, "inlier_ratio": np.nan}
                         for s, i, j, n, c, r in rows], columns=list(PAIR_COLUMNS))


# fragments: a0/a1 large (300 points), b0/b1 small (80), c0 medium (150)
POINTS = {("a", 0): 300, ("a", 1): 300, ("b", 0): 80, ("b", 1): 80, ("c", 0): 150, ("c", 1): 300}


def test_the_table_counts_each_regime_and_follows_the_pairs_uniform_at_the_largest_n():
    rows = []
    for n, (rb, rc) in ((200, (0, 0)), (100, (1, 0)), (50, (1, 1))):  # pair a always registers
        rows += [("a", 0, 1, n, 1, 1), ("b", 0, 1, n, 1, rb), ("c", 0, 1, n, 1, rc), ("a", 1, 0, n, 0, 0)]
    t = regime_table(_pairs(rows), POINTS)
    assert list(t.columns) == list(COLUMNS)
    assert t["n_points"].tolist() == [200, 100, 50]
    assert t["pairs"].tolist() == [3, 3, 3]  # the uncounted pair is left out
    # N=200: a scores, c mixed (150 <= 200 < 300), b uniform; N=100: a, c scores, b uniform; N=50: all scores
    assert t[["n_scores", "n_mixed", "n_uniform"]].values.tolist() == [[1, 1, 1], [2, 0, 1], [3, 0, 0]]
    assert t["rr"].round(6).tolist() == [round(100 / 3, 6), round(200 / 3, 6), 100.0]
    assert t["rr_uniform"].tolist()[:2] == [0.0, 100.0] and np.isnan(t["rr_uniform"].iloc[2])
    assert t["rr_mixed"].iloc[0] == 0.0 and np.isnan(t["rr_mixed"].iloc[1])
    # the pairs uniform at 200 (b) followed to the smaller N, where the scores sample them
    assert t["rr_fixed"].tolist() == [0.0, 100.0, 100.0]
    text = format_table(t, "demo")
    assert text.startswith("### demo") and "RR of the pairs uniform at 200" in text and "| 200 | 3 | 1 | 1 | 1 |" in text


def test_bad_outcomes_name_what_is_missing():
    with pytest.raises(ValueError, match="no point count for fragment \\('z', 0\\)"):
        regime_table(_pairs([("z", 0, 1, 100, 1, 1)]), POINTS)
    with pytest.raises(ValueError, match="without n_points"):
        regime_table(_pairs([("a", 0, 1, None, 1, 1)]).astype({"n_points": float}), POINTS)
    with pytest.raises(ValueError, match="lack the columns \\['registered'\\]"):
        regime_table(_pairs([("a", 0, 1, 100, 1, 1)]).drop(columns="registered"), POINTS)


def _fragment(path: Path, cells: int) -> None:
    """A fragment whose grid subsampling at VOXEL keeps ``cells`` points (two points in each cell)."""
    centres = (np.arange(cells)[:, None] * np.array([[VOXEL, 0.0, 0.0]]) + VOXEL / 2).astype(np.float32)
    write_ply(path, np.concatenate([centres - 0.01, centres + 0.01]))


def test_model_points_counts_the_grid_cells_the_network_keeps(tmp_path):
    _fragment(tmp_path / "f.ply", 37)
    assert model_points(tmp_path / "f.ply", VOXEL) == 37


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A store with one run of the learned model: outcomes on 3DLoMatch, fragments of POINTS in its data.root."""
    from pcrcg.tracking.store import ensure_store
    from pcrcg.tracking.tracker import RunTracker

    monkeypatch.chdir(tmp_path)
    layout = Layout(tmp_path / "data")
    for (scene, i), n in POINTS.items():
        layout.fragments_dir(scene).mkdir(parents=True, exist_ok=True)
        _fragment(layout.fragment(scene, i), n)
    csv = tmp_path / "art" / "pairs" / "3DLoMatch.csv"
    csv.parent.mkdir(parents=True)
    _pairs([(s, 0, 1, n, 1, int(s == "a" or n < 100)) for n in (200, 100, 50) for s in "abc"]).to_csv(csv, index=False)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    ensure_store(uri)
    tr = RunTracker(uri, "main_results")
    rid = tr.start("Predator", {"experiment": "main_results", "config_hash": "x"})
    tr.log_params(rid, {"model.voxel_size": VOXEL, "data.root": "data"})
    tr.log_artifact(rid, csv.parent, "pairs")
    tr.finish(rid)
    return uri, rid


def test_the_command_reads_a_tracked_runs_outcomes_and_its_fragments(store, tmp_path):
    uri, rid = store
    out: list[str] = []
    assert main([rid[:6], "--tracking-uri", uri, "--no-progress", "--out", "s.md"], echo=out.append) == 0
    text = out[0]
    assert f"### run {rid[:8]}, 3DLoMatch" in text and "3DMatch" not in text  # no outcomes on 3DMatch: left out
    assert "| 200 | 3 | 1 | 1 | 1 | 33.3 | 100.0 | 0.0 | 0.0 | 0.0 |" in text
    assert "| 50 | 3 | 3 | 0 | 0 | 100.0 | 100.0 | — | — | 100.0 |" in text
    assert (tmp_path / "s.md").read_text() == text


def test_the_command_refuses_unknown_runs_and_missing_fragments_in_one_line(store, tmp_path, capsys):
    uri, rid = store
    assert main(["nosuchrun", "--tracking-uri", uri, "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "RUN='nosuchrun'" in err
    (Layout(tmp_path / "data").fragment("c", 1)).unlink()
    assert main([rid, "--tracking-uri", uri, "--no-progress", "--out", "s.md"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cloud_bin_1" in err and not (tmp_path / "s.md").exists()
