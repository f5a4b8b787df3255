"""`prepare` end to end at the tiny profile, the layout it writes, reuse/atomicity, and bad input."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, compose, shared_path, tiny_data_cfg
from pcrcg.data import materialise
from pcrcg.data.checks import check_dataset, check_layout
from pcrcg.data.dataset import PairDataset, benchmark_pairs
from pcrcg.data.fusion import FusionConfig
from pcrcg.data.layout import Layout, read_gt_log, read_pairs, read_split, write_matrix
from pcrcg.data.materialise import prepare_dataset, read_manifest
from pcrcg.data.pairs import PairConfig
from pcrcg.data.synth.render import SensorModel
from pcrcg.data.synthmatch import SynthConfig, generate_scene
from pcrcg.errors import ConfigError, DataError
from pcrcg.geometry import transform_points


def _marking_job(calls: list):
    """A stand-in for the generator: records its seed in ``calls`` and writes it to ``marker``."""

    def job(tmp, data_cfg, seed, log):
        calls.append(seed)
        (tmp / "marker").write_text(str(seed))
        return {"pairs": {"3DMatch": 1, "3DLoMatch": 1}}

    return job


def test_tiny_has_train_pairs_and_both_benchmarks(tiny_root):
    stats = read_manifest(tiny_root)["stats"]
    assert stats["scenes"] == {"train": 2, "val": 1, "test": 1}
    assert stats["pairs"]["train"] > 5 and stats["pairs"]["val"] > 0
    assert stats["pairs"]["3DMatch"] > 0 and stats["pairs"]["3DLoMatch"] > 0
    layout = Layout(tiny_root)
    assert set(read_split(layout.split_file("test"))).isdisjoint(read_split(layout.split_file("train")))
    assert check_layout(tiny_root) == []


def test_tiny_is_self_consistent(tiny_root):
    """Pose/gt.log agreement, overlaps, gt.info and depth agreement, recomputed from the files."""
    rep = check_dataset(tiny_root)
    assert rep.ok, rep.failed
    assert rep.not_applicable == []  # this project wrote every file: everything is re-derived
    assert rep.measures["pose_max_abs"] < 1e-6
    assert rep.measures["overlap_max_abs"] < 1e-3  # same code; gt.log stores 11 digits
    assert rep.measures["depth_median_abs_max"] < 0.03


def test_benchmark_overlaps_follow_the_split(tiny_root):
    layout = Layout(tiny_root)
    for bench, lo, hi in (("3DMatch", 0.3, 1.0), ("3DLoMatch", 0.1, 0.3)):
        for p in benchmark_pairs(layout, bench):
            assert lo <= p.overlap <= hi + 1e-9
            assert p.i < p.j
    for p in read_pairs(layout.pairs_file("train")):
        assert p.overlap >= 0.1


def test_pair_dataset_sample(tiny_root):
    ds = PairDataset(tiny_root, "3DMatch", n_views=3)
    s = ds[0]
    assert s.src_points.shape[1] == 3 and s.src_points.dtype == np.float32
    assert s.src_colors.shape == s.src_points.shape and 0 <= s.src_colors.min() and s.src_colors.max() <= 1
    assert len(s.src_views) == 3 and len(s.tgt_views) == 3
    first, last, middle = s.tgt_views
    assert first.frame_id < middle.frame_id < last.frame_id
    np.testing.assert_allclose(first.pose, np.eye(4), atol=1e-9)  # fragment frame = first camera
    assert first.color.shape[:2] == first.depth.shape == (120, 160)
    # the ground truth brings the source onto the target
    from scipy.spatial import cKDTree

    d, _ = cKDTree(s.tgt_points).query(transform_points(s.transform, s.src_points))
    assert np.mean(d < 0.0375) > 0.3 * 0.8
    assert len(PairDataset(tiny_root, "train", n_views=0)[0].src_views) == 0


def test_frames_only_writes_the_full_builds_frames_and_nothing_else(tiny_root, tmp_path):
    """``data=synthmatch_pretrain`` (the 2D pretraining's rooms) renders the frames only: the same files, byte for
    byte, as the full build of the same seed, and the splits; no fragments, pairs or benchmarks. A value that is not
    a boolean is named before any work."""
    root = prepare_dataset(tiny_data_cfg(tmp_path / "frames", "data=synthmatch_pretrain"), seed=0, log=lambda m: None)

    def files(r, sub):
        return sorted(p.relative_to(r) for p in (r / sub).rglob("*") if p.is_file())

    ours = files(root, "rgbd")
    assert ours == files(tiny_root, "rgbd") and len(ours) > 50
    assert all((root / p).read_bytes() == (tiny_root / p).read_bytes() for p in ours)
    layout, full = Layout(root), Layout(tiny_root)
    for split in ("train", "val", "test"):
        assert read_split(layout.split_file(split)) == read_split(full.split_file(split))
    assert files(root, "fragments") == [] and files(root, "benchmarks") == []
    stats = read_manifest(root)["stats"]
    assert stats["fragments"] == 0 and stats["frames"] == read_manifest(tiny_root)["stats"]["frames"]
    assert read_manifest(root)["params"]["frames_only"] is True
    with pytest.raises(ConfigError, match="data.frames_only"):
        prepare_dataset(tiny_data_cfg(tmp_path / "bad", "+data.frames_only=3"), seed=0, log=lambda m: None)
    assert list(tmp_path.glob("bad*")) == []  # named before anything is written


def test_reuse_and_regenerate(tiny_root, tmp_path, monkeypatch):
    before = read_manifest(tiny_root)
    again = prepare_dataset(tiny_data_cfg(tiny_root), seed=0, log=lambda m: None)
    assert again == tiny_root and read_manifest(tiny_root)["created"] == before["created"]

    # different parameters: regenerated (here by a stand-in job, to stay fast)
    root = tmp_path / "d"
    calls = []

    monkeypatch.setattr(materialise, "_prepare_synthmatch", _marking_job(calls))
    cfg = tiny_data_cfg(root)
    prepare_dataset(cfg, seed=1, log=lambda m: None)
    prepare_dataset(cfg, seed=1, log=lambda m: None)
    assert calls == [1]
    prepare_dataset(cfg, seed=2, log=lambda m: None)
    assert calls == [1, 2] and (root / "marker").read_text() == "2"


def test_interrupted_generation_keeps_the_old_data_set(tmp_path, monkeypatch):
    root = tmp_path / "d"

    def ok_job(tmp, data_cfg, seed, log):
        (tmp / "marker").write_text("old")
        return {}

    def failing_job(tmp, data_cfg, seed, log):
        (tmp / "half-written").write_text("x")
        raise KeyboardInterrupt

    cfg = tiny_data_cfg(root)
    monkeypatch.setattr(materialise, "_prepare_synthmatch", ok_job)
    prepare_dataset(cfg, seed=1, log=lambda m: None)
    monkeypatch.setattr(materialise, "_prepare_synthmatch", failing_job)
    with pytest.raises(KeyboardInterrupt):
        prepare_dataset(cfg, seed=2, log=lambda m: None)
    assert (root / "marker").read_text() == "old"
    assert read_manifest(root)["params"]["seed"] == 1
    assert not list(tmp_path.glob("d.tmp-*"))  # nothing half-written left behind


def test_a_root_this_build_did_not_write_is_never_replaced(tmp_path, monkeypatch):
    """A user's folder (files, no manifest), a file, and a data set of another source are refused
    before any work, and left as they were; an empty folder and the same source's data set are built."""
    calls = []

    def job(tmp, data_cfg, seed, log):
        calls.append(seed)
        return {}

    monkeypatch.setattr(materialise, "_prepare_synthmatch", job)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("years of work")
    with pytest.raises(ConfigError, match=r"data.root=.*mine.*no manifest.json.*nothing was changed"):
        prepare_dataset(tiny_data_cfg(mine), seed=1, log=lambda m: None)
    assert (mine / "thesis.tex").read_text() == "years of work" and calls == []

    a_file = tmp_path / "notes.txt"
    a_file.write_text("x")
    with pytest.raises(ConfigError, match=r"data.root=.*notes.txt.*a folder"):
        prepare_dataset(tiny_data_cfg(a_file), seed=1, log=lambda m: None)
    assert a_file.read_text() == "x"

    real = tmp_path / "real"
    real.mkdir()
    (real / "manifest.json").write_text(json.dumps({"params_hash": "0", "params": {"name": "threedmatch"}}))
    (real / "fragments").mkdir()
    with pytest.raises(ConfigError, match=r"data.root=.*real.*holds a threedmatch data set.*data=threedmatch"):
        prepare_dataset(tiny_data_cfg(real), seed=1, log=lambda m: None)
    assert (real / "fragments").is_dir() and read_manifest(real)["params"]["name"] == "threedmatch"
    assert calls == []

    empty = tmp_path / "empty"
    empty.mkdir()
    prepare_dataset(tiny_data_cfg(empty), seed=1, log=lambda m: None)
    prepare_dataset(tiny_data_cfg(empty), seed=2, log=lambda m: None)  # same source, new params: rebuilt
    assert calls == [1, 2] and read_manifest(empty)["params"]["seed"] == 2


def test_a_test_only_sample_is_prepared_and_a_run_that_would_train_on_it_is_refused_first(tmp_path):
    """Sizes that leave no training scene (n_val + n_test = n_scenes) make a test-only data set, as the real
    scene's (for statistics of a profile's data without its training rooms); a training run with such sizes is
    refused by the preflight, before any generation."""
    from pcrcg.config import preflight

    sizes = ("profile.synth.n_scenes=1", "profile.synth.n_val=0", "profile.synth.n_test=1")
    root = prepare_dataset(tiny_data_cfg(tmp_path / "sample", *sizes), seed=0, log=lambda m: None)
    stats = read_manifest(root)["stats"]
    assert stats["scenes"] == {"train": 0, "val": 0, "test": 1} and stats["pairs"]["train"] == 0
    assert stats["pairs"]["3DMatch"] > 0 and read_pairs(Layout(root).pairs_file("train")) == []
    run = compose("run", ["profile=tiny", f"data.root={tmp_path / 'other'}", *sizes])
    with pytest.raises(ConfigError, match=r"data.synth.n_scenes=1.*more than n_val \+ n_test = 1"):
        preflight(run)
    preflight(compose("run", ["profile=tiny", "method=fpfh", *sizes]))  # a classical method trains nothing
    assert not (tmp_path / "other").exists()


def test_same_seed_same_bytes(tmp_path):
    cfg = SynthConfig(n_scenes=1, n_val=0, n_test=0, width=64, height=48, fragments_per_scene=2,
                      frames_per_fragment=2)
    args = (0, 5, cfg, SensorModel(), FusionConfig(tsdf_voxel=0.05, fragment_voxel=0.05, min_weight=1), PairConfig(), True)
    generate_scene(str(tmp_path / "a"), *args)
    generate_scene(str(tmp_path / "b"), *args)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) > 10
    for f in files_a:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    other = generate_scene(str(tmp_path / "c"), 0, 6, *args[2:])
    assert (tmp_path / "c" / files_a[-1]).exists() and other.n_fragments == 2
    assert (tmp_path / "c/rgbd/synth-000/seq-01/frame-000000.color.png").read_bytes() != \
        (tmp_path / "a/rgbd/synth-000/seq-01/frame-000000.color.png").read_bytes()


def test_invalid_profile_values_name_the_setting(tmp_path):
    with pytest.raises(ConfigError, match="data.synth.width"):
        prepare_dataset(tiny_data_cfg(tmp_path / "x", "profile.synth.width=0"), log=lambda m: None)
    with pytest.raises(ConfigError, match="data.synth.n_scenes"):
        prepare_dataset(tiny_data_cfg(tmp_path / "x", "profile.synth.n_test=4"), log=lambda m: None)
    with pytest.raises(ConfigError, match="data.fusion.bogus"):
        prepare_dataset(tiny_data_cfg(tmp_path / "x", "+data.fusion.bogus=1"), log=lambda m: None)
    for bad in ("[0.6,0.3]", "[0.2]", "[0.2,1.5]", "abc"):
        with pytest.raises(ConfigError, match="data.synth.outward_radius"):
            prepare_dataset(tiny_data_cfg(tmp_path / "x", f"+profile.synth.outward_radius={bad}"), log=lambda m: None)
    assert not (tmp_path / "x").exists()


def test_cli_reports_bad_setting_before_work(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pcrcg.prepare", "profile=tiny", f"data.root={tmp_path / 'x'}",
                        "profile.synth.frames_per_fragment=0"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    # one line, naming the key the user set (data.synth is ${profile.synth})
    assert r.stderr.strip().splitlines() == [
        "pcrcg.prepare: error: invalid config value profile.synth.frames_per_fragment=0: allowed a positive integer"]
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------- real frames


def _frames_copy(tmp_path, n=16):
    src = shared_path("data", "real-rgbd", "redkitchen-frames")
    dst = tmp_path / "frames"
    dst.mkdir()
    shutil.copy2(src / "camera-intrinsics.txt", dst)
    for p in sorted(src.glob("frame-*"))[: 3 * n]:
        shutil.copy2(p, dst)
    return dst


def _real_cfg(tmp_path, frames_dir, *extra):
    from omegaconf import OmegaConf

    cfg = compose("prepare", ["data=redkitchen", f"data.root={tmp_path / 'out'}", f"data.frames_dir={frames_dir}", *extra])
    return OmegaConf.to_container(cfg.data, resolve=True)


@pytest.mark.parametrize("damage,match", [
    ("truncate", "frame-000012.depth.png.*truncated"),
    ("corrupt", "frame-000012.color.png.*decode"),
    ("nan_pose", "frame-000012.pose.txt.*NaN"),
    ("missing", "frame-000012.depth.png.*missing"),
    ("small_depth", "frame-000012.depth.png.*depth is 320x240 but color is 640x480"),
])
def test_real_frames_bad_input_is_named_before_fusion(tmp_path, damage, match, monkeypatch):
    import cv2

    frames = _frames_copy(tmp_path, n=10)
    d = frames / "frame-000012.depth.png"
    if damage == "truncate":
        d.write_bytes(d.read_bytes()[:5000])
    elif damage == "corrupt":
        (frames / "frame-000012.color.png").write_bytes(b"\x89PNG garbage")
    elif damage == "nan_pose":
        T = np.eye(4)
        T[1, 3] = np.nan
        write_matrix(frames / "frame-000012.pose.txt", T)
    elif damage == "missing":
        d.unlink()
    else:
        img = cv2.imread(str(d), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(d), img[::2, ::2])
    fused = []
    monkeypatch.setattr("pcrcg.data.build.fuse_frames", lambda *a, **k: fused.append(1))
    with pytest.raises(DataError, match=match):
        prepare_dataset(_real_cfg(tmp_path, frames), log=lambda m: None)
    assert fused == []  # nothing fused before the check failed
    assert not (tmp_path / "out").exists()


def test_real_frames_missing_folder(tmp_path):
    with pytest.raises(DataError, match="nowhere.*data.frames_dir"):
        prepare_dataset(_real_cfg(tmp_path, tmp_path / "nowhere"), log=lambda m: None)


@pytest.mark.slow
def test_redkitchen_fuses_like_generated_data(tmp_path):
    src = shared_path("data", "real-rgbd", "redkitchen-frames")
    root = prepare_dataset(_real_cfg(tmp_path, src), log=lambda m: None)
    stats = read_manifest(root)["stats"]
    assert stats["fragments"] == 5 and stats["points_per_fragment"]["min"] > 5000
    rep = check_dataset(root)
    assert rep.ok, rep.failed
    assert rep.measures["depth_median_abs_max"] < 0.02


# --------------------------------------------------------------------------- the real release's layout


def _fake_release(tmp_path, n_frag=4):
    """Fragments as Predator's .pth arrays plus benchmark files, for two scenes."""
    import torch

    rng = np.random.default_rng(0)
    frag_dir, bench_dir = tmp_path / "fragments", tmp_path / "benchmarks"
    for scene in ("kitchen", "office"):
        (frag_dir / scene).mkdir(parents=True)
        for i in range(n_frag):
            torch.save(rng.normal(size=(500, 3)).astype(np.float32), frag_dir / scene / f"cloud_bin_{i}.pth")
        for bench, pairs in (("3DMatch", [(0, 1), (0, 2)]), ("3DLoMatch", [(1, 3)])):
            d = bench_dir / bench / scene
            d.mkdir(parents=True)
            with open(d / "gt.log", "w") as f:
                for i, j in pairs:
                    f.write(f"{i}\t{j}\t{n_frag}\n" + "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
            with open(d / "gt.info", "w") as f:
                for i, j in pairs:
                    f.write(f"{i}\t{j}\t{n_frag}\n" + "".join(" ".join("1" if a == b else "0" for b in range(6)) + "\n" for a in range(6)))
            (d / "gt_overlap.log").write_text("".join(f"{i},{j},0.5\n" for i in range(n_frag) for j in range(i + 1, n_frag)))
    return frag_dir, bench_dir


def _release_cfg(tmp_path, frag_dir, bench_dir):
    from omegaconf import OmegaConf

    cfg = compose("prepare", ["data=threedmatch", f"data.root={tmp_path / 'out'}",
                              f"data.source.fragments_dir={frag_dir}", f"data.source.benchmarks_dir={bench_dir}"])
    return OmegaConf.to_container(cfg.data, resolve=True)


def test_threedmatch_release_is_converted(tmp_path):
    frag_dir, bench_dir = _fake_release(tmp_path)
    root = prepare_dataset(_release_cfg(tmp_path, frag_dir, bench_dir), log=lambda m: None)
    assert read_split(Layout(root).split_file("test")) == ["kitchen", "office"]
    ds = PairDataset(root, "3DMatch")
    assert len(ds) == 4
    s = ds[0]
    import torch

    np.testing.assert_allclose(s.tgt_points, torch.load(frag_dir / "kitchen/cloud_bin_0.pth", weights_only=False), atol=1e-6)
    assert len(read_gt_log(Layout(root).benchmark_dir("3DLoMatch", "office") / "gt.log")) == 1


def test_threedmatch_missing_fragment_drops_its_pairs(tmp_path):
    """A partial release builds the pairs it can (see tests/test_data_release.py); none is an error."""
    frag_dir, bench_dir = _fake_release(tmp_path)
    (frag_dir / "office" / "cloud_bin_3.pth").unlink()
    root = prepare_dataset(_release_cfg(tmp_path, frag_dir, bench_dir), log=lambda m: None)
    assert read_manifest(root)["stats"]["pairs"] == {"3DMatch": 4, "3DLoMatch": 1}
    assert not (Layout(root).benchmark_dir("3DLoMatch", "office")).exists()
    for p in frag_dir.glob("*/cloud_bin_*.pth"):
        p.unlink()
    with pytest.raises(DataError, match="no official pair has both fragments available"):
        prepare_dataset(_release_cfg(tmp_path / "again", frag_dir, bench_dir), log=lambda m: None)
    assert not (tmp_path / "again" / "out").exists()


def test_threedmatch_official_benchmark_files_are_read(tmp_path):
    """The official files of ../shared with stand-in fragments: every pair is found and kept."""
    bench = shared_path("data", "3dmatch-benchmarks")
    import torch

    frag_dir = tmp_path / "fragments"
    needed = {}
    for b in ("3DMatch", "3DLoMatch"):
        for d in (bench / b).iterdir():
            for r in read_gt_log(d / "gt.log"):
                needed.setdefault(d.name, set()).update((r.i, r.j))
    pts = np.zeros((10, 3), np.float32)
    for scene, ids in needed.items():
        (frag_dir / scene).mkdir(parents=True)
        for i in ids:
            torch.save(pts, frag_dir / scene / f"cloud_bin_{i}.pth")
    root = prepare_dataset(_release_cfg(tmp_path, frag_dir, bench), log=lambda m: None)
    assert read_manifest(root)["stats"]["pairs"] == {"3DMatch": 1623, "3DLoMatch": 1781}
    assert json.loads((root / "manifest.json").read_text())["stats"]["scenes"]["test"] == 8


@pytest.mark.shared
def test_real_frames_keep_the_color_camera_and_bad_values_are_named(tmp_path):
    from pcrcg.data.layout import Layout, read_intrinsics
    from pcrcg.errors import ConfigError

    frames = _frames_copy(tmp_path, n=3)
    with pytest.raises(ConfigError, match="data.color_intrinsics"):
        prepare_dataset(_real_cfg(tmp_path, frames, "data.color_intrinsics=[525,0,320,240]", "data.frames_per_fragment=3"),
                        log=lambda m: None)
    root = prepare_dataset(_real_cfg(tmp_path, frames, "data.frames_per_fragment=3"), log=lambda m: None)
    lay = Layout(root)
    Kc = read_intrinsics(lay.color_intrinsics("7-scenes-redkitchen"))
    assert Kc[0, 0] == 525.0 and read_intrinsics(lay.intrinsics("7-scenes-redkitchen"))[0, 0] == 585.0


def test_a_run_refuses_a_data_set_made_with_other_parameters_and_prepare_replaces_it(tmp_path, monkeypatch):
    """``python -m pcrcg.run profile=paper data.root=data/synthmatch-cpu`` generated a paper-sized set for hours and
    then deleted the cpu one. A run now refuses, before any work, with one line naming data.root and what differs;
    ``python -m pcrcg.prepare`` (replace=True, its job) still replaces it."""
    calls = []

    monkeypatch.setattr(materialise, "_prepare_synthmatch", _marking_job(calls))
    root = tmp_path / "held"
    prepare_dataset(tiny_data_cfg(root), seed=1, log=lambda m: None)
    wanted = tiny_data_cfg(root, "profile.synth.width=40")
    with pytest.raises(ConfigError, match=r"data.root=.*held.*made with other parameters \(seed: 1 -> 2, "
                                          r"synth.width: \d+ -> 40\).*pcrcg.prepare.*nothing was changed"):
        prepare_dataset(wanted, seed=2, log=lambda m: None, replace=False)
    assert calls == [1] and (root / "marker").read_text() == "1"
    assert read_manifest(root)["params"]["seed"] == 1
    assert prepare_dataset(tiny_data_cfg(root), seed=1, log=lambda m: None, replace=False) == root  # same: reused
    assert materialise.param_differences({"a": {"b": 1, "c": 2}, "d": 3}, {"a": {"b": 1, "c": 5}, "e": 4}, limit=2) \
        == "a.c: 2 -> 5, d: 3 -> (none), 1 more"

    # the run's data stage, through the command line: exit 2, one line, the data set untouched, nothing trained
    res = subprocess.run([sys.executable, "-m", "pcrcg.run", "profile=tiny", f"data.root={root}", "profile.synth.width=40",
                          f"hydra.run.dir={tmp_path}/out", f"paths.checkpoints={tmp_path}/ckpt"], cwd=REPO,
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db"})
    err = res.stderr.strip().splitlines()
    assert res.returncode == 2 and err[-1].startswith("pcrcg.run: error: invalid config value data.root="), err[-3:]
    assert "synth.width" in err[-1] and "seed: 1 -> 0" in err[-1]
    assert (root / "marker").read_text() == "1" and read_manifest(root)["params"]["seed"] == 1
    assert not (tmp_path / "ckpt").exists() and not list(tmp_path.glob("held.tmp-*"))

    prepare_dataset(wanted, seed=2, log=lambda m: None)  # python -m pcrcg.prepare's call: replaced
    assert calls == [1, 2] and (root / "marker").read_text() == "2"
