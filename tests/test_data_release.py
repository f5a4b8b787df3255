"""Real 3DMatch data through the same code: jpg frames, Predator's legacy `.pth` fragments (read
without executing code), and `data=threedmatch` built from a partial release (fragments read where
given, fused from the release's RGB-D frames where not; only the official pairs that can be built)."""

from __future__ import annotations

import io
import os
import pickle
import time

import numpy as np
import pytest

from conftest import SHARED, compose, shared_path
from pcrcg.data.dataset import PairDataset, load_views
from pcrcg.data.layout import (
    FragmentInfo,
    Layout,
    PairRecord,
    frame_ids,
    frame_paths,
    read_cloud,
    read_color,
    read_fragment_info,
    read_gt_log,
    write_color,
    write_depth,
    write_fragment_info,
    write_gt_info,
    write_gt_log,
    write_gt_overlap,
    write_matrix,
    write_ply,
)
from pcrcg.data.materialise import prepare_dataset, read_manifest
from pcrcg.data.release import fusion_from
from pcrcg.errors import ConfigError, DataError
from pcrcg.geometry import invert, make_transform

RELEASE = SHARED / "data" / "real-3dmatch-fragments" / "7-scenes-redkitchen"
FRAMES = SHARED / "data" / "real-rgbd" / "7-scenes-redkitchen"


# --------------------------------------------------------------------------- jpg frames


def test_jpg_frames_are_found_read_and_truncation_is_named(tmp_path):
    v, u = np.mgrid[0:24, 0:32]
    rgb = np.stack([u * 8, v * 10, np.full_like(u, 200)], axis=-1).astype(np.uint8)  # smooth: jpg keeps it
    write_color(tmp_path / "frame-000003.color.jpg", rgb)
    write_color(tmp_path / "frame-000001.color.png", rgb)
    (tmp_path / "frame-000002.depth.png").write_bytes(b"")  # not a color frame
    assert frame_ids(tmp_path) == [1, 3]
    assert frame_paths(tmp_path / "frame-000003")[0].name == "frame-000003.color.jpg"
    assert frame_paths(tmp_path / "frame-000001")[0].name == "frame-000001.color.png"
    assert frame_paths(tmp_path / "frame-000009")[0].name == "frame-000009.color.png"  # absent: the usual name
    img = read_color(tmp_path / "frame-000003.color.jpg")
    assert img.shape == (24, 32, 3) and img.dtype == np.uint8
    assert np.abs(img.astype(int) - rgb).mean() < 6  # lossy, but the same picture, RGB order
    # a truncated jpg: one line naming the file (OpenCV alone would decode it with gray rows)
    raw = (tmp_path / "frame-000003.color.jpg").read_bytes()
    bad = tmp_path / "frame-000004.color.jpg"
    bad.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match="frame-000004.color.jpg: JPEG is truncated") as exc:
        read_color(bad)
    assert "\n" not in str(exc.value)
    # zero padding after the end-of-image marker is fine
    bad.write_bytes(raw + b"\x00" * 16)
    read_color(bad)


@pytest.mark.shared
def test_the_release_jpg_frames_read():
    seq = shared_path("data", "real-rgbd", "7-scenes-redkitchen", "seq-01")
    ids = frame_ids(seq)
    assert ids[0] == 0 and len(ids) >= 50
    color = read_color(frame_paths(seq / "frame-000000")[0])
    assert color.shape == (480, 640, 3)


# --------------------------------------------------------------------------- legacy .pth


def test_legacy_pth_of_a_numpy_array_is_read(tmp_path):
    import torch

    pts = np.random.default_rng(1).normal(size=(200, 3))  # float64, as Predator's release
    torch.save(pts, tmp_path / "legacy.pth", _use_new_zipfile_serialization=False)
    torch.save(pts, tmp_path / "zip.pth")
    for name in ("legacy.pth", "zip.pth"):
        got, cols = read_cloud(tmp_path / name)
        assert got.shape == (200, 3) and got.dtype == np.float32 and cols is None
        np.testing.assert_allclose(got, pts, atol=1e-6)


class _Evil:
    """Unpickling this would run a shell command."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _legacy_bytes(obj_pickle: bytes) -> bytes:
    """torch.save's legacy layout: magic, protocol, system info, the object, the storage keys."""
    buf = io.BytesIO()
    for head in (0x1950A86A20F9469CFC6C, 1001, {"protocol_version": 1001, "little_endian": True,
                                                "type_sizes": {"short": 2, "int": 4, "long": 4}}):
        pickle.dump(head, buf, protocol=2)
    buf.write(obj_pickle)
    pickle.dump([], buf, protocol=2)
    return buf.getvalue()


def test_a_crafted_pth_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "pwned"
    evil = pickle.dumps(_Evil(marker), protocol=2)
    (tmp_path / "legacy.pth").write_bytes(_legacy_bytes(evil))
    (tmp_path / "plain.pth").write_bytes(evil)
    for name in ("legacy.pth", "plain.pth"):
        with pytest.raises(DataError, match=f"{name}: cannot read .pth safely: global .*system is not allowed") as exc:
            read_cloud(tmp_path / name)
        assert "\n" not in str(exc.value)
    assert not marker.exists()
    # an object that is not an array of points
    (tmp_path / "dict.pth").write_bytes(_legacy_bytes(pickle.dumps({"a": 1}, protocol=2)))
    with pytest.raises(DataError, match="dict.pth: dict in .pth has no 'points'"):
        read_cloud(tmp_path / "dict.pth")


@pytest.mark.shared
@pytest.mark.parametrize("k", [0, 5])
def test_the_release_pth_fragments_match_their_ply(k):
    from pcrcg.data.pairs import voxel_downsample

    d = shared_path("data", "real-3dmatch-fragments", "7-scenes-redkitchen")
    pth, _ = read_cloud(d / f"cloud_bin_{k}.pth")
    ply, _ = read_cloud(d / f"cloud_bin_{k}.ply")
    assert pth.ndim == 2 and pth.shape[1] == 3 and 10_000 < len(pth) < 30_000
    np.testing.assert_allclose(pth.min(0), ply.min(0), atol=0.025)
    np.testing.assert_allclose(pth.max(0), ply.max(0), atol=0.025)
    n = len(voxel_downsample(ply, 0.025))
    assert 0.7 < len(pth) / n < 1.3  # 2.5 cm, as Predator prepared it


# --------------------------------------------------------------------------- .info.txt


def test_both_info_formats_parse(tmp_path):
    ours = tmp_path / "cloud_bin_3.info.txt"
    write_fragment_info(ours, FragmentInfo("scene", "seq-01", 150, 199), extra="# 50 frames fused\n")
    release = tmp_path / "cloud_bin_0.info.txt"  # "scene seq first last" (tabs), then the 4x4 pose
    release.write_text("7-scenes-redkitchen\t seq-01\t 0\t 49\t\n" + "".join(
        "\t".join(f"{v: .8e}" for v in row) + "\t\n" for row in np.eye(4)))
    assert read_fragment_info(ours) == FragmentInfo("scene", "seq-01", 150, 199)
    assert read_fragment_info(release).frame_ids() == list(range(50))
    if (RELEASE / "cloud_bin_5.info.txt").is_file():
        assert read_fragment_info(RELEASE / "cloud_bin_5.info.txt") == FragmentInfo(
            "7-scenes-redkitchen", "seq-01", 250, 299)


# --------------------------------------------------------------------------- partial release


W, H, FPF = 64, 48, 2
K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])


def _pose(f: int) -> np.ndarray:
    """Camera-to-world of frame f: a camera sliding along x, looking along +z."""
    return make_transform(np.eye(3), [0.04 * f, 0.01 * f, 0.0])


def _depth(f: int) -> np.ndarray:
    """Depth (H, W) of frame f: a wall at z = 1.5 m and a box face at z = 1.2 m (world frame)."""
    t = _pose(f)[:3, 3]
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    x = t[0] + 1.2 * (u - K[0, 2]) / K[0, 0]
    y = t[1] + 1.2 * (v - K[1, 2]) / K[1, 1]
    box = (np.abs(x) < 0.25) & (y > -0.2) & (y < 0.1)
    return np.where(box, 1.2, 1.5).astype(np.float32)


def _fake_release(tmp_path, missing_frame: int | None = 7):
    """Scene `kitchen` with 4 fragments of 2 frames: 0 as a legacy .pth, 1 as .ply, 2 and 3 only as
    frames (one of fragment 3's frames missing); scene `office` with no fragment at all."""
    import torch

    from pcrcg.data.build import fuse_sequence
    from pcrcg.data.fusion import FusionConfig

    rgbd = tmp_path / "rgbd"
    seq = rgbd / "kitchen" / "seq-01"
    seq.mkdir(parents=True)
    write_matrix(rgbd / "kitchen" / "camera-intrinsics.txt", K)
    rng = np.random.default_rng(0)
    for f in range(4 * FPF):
        if f == missing_frame:
            continue
        write_color(seq / f"frame-{f:06d}.color.jpg", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        write_depth(seq / f"frame-{f:06d}.depth.png", _depth(f))
        write_matrix(seq / f"frame-{f:06d}.pose.txt", _pose(f))
    # fragments 0 and 1 "from the release": fused here from the same frames, then saved as files
    scratch = Layout(tmp_path / "scratch")
    scratch.rgbd_dir("kitchen").parent.mkdir(parents=True)
    os.symlink(rgbd / "kitchen", scratch.rgbd_dir("kitchen"))
    fr = tmp_path / "fragments" / "kitchen"
    fr.mkdir(parents=True)
    for k in (0, 1):
        (pts,), _ = fuse_sequence(scratch, "kitchen", "seq-01", range(FPF * k, FPF * k + FPF), FPF,
                                  FusionConfig(tsdf_voxel=0.02, min_weight=1, fragment_voxel=0.0), first_index=k)
        if k == 0:
            torch.save(pts.astype(np.float64), fr / "cloud_bin_0.pth", _use_new_zipfile_serialization=False)
        else:
            write_ply(fr / "cloud_bin_1.ply", pts)
    bench = tmp_path / "benchmarks"
    pairs = {"3DMatch": [(0, 1), (0, 2), (1, 2), (2, 3)], "3DLoMatch": [(0, 3), (1, 3)]}
    for b, ijs in pairs.items():
        for scene in ("kitchen", "office"):
            d = bench / b / scene
            d.mkdir(parents=True)
            recs = [PairRecord(scene, i, j, invert(_pose(FPF * i)) @ _pose(FPF * j), 0.5, 4) for i, j in ijs]
            write_gt_log(d / "gt.log", recs)
            write_gt_info(d / "gt.info", recs, [np.eye(6) * 100 for _ in recs])
            write_gt_overlap(d / "gt_overlap.log", [PairRecord(scene, i, j, np.eye(4), 0.5) for i in range(4)
                                                    for j in range(i + 1, 4)])
    return fr.parent, rgbd, bench


def _release_cfg(root, fragments, rgbd, bench, *extra):
    from omegaconf import OmegaConf

    cfg = compose("prepare", ["data=threedmatch", f"data.root={root}", f"data.source.benchmarks_dir={bench}",
                              f"data.source.fragments_dir={fragments}", f"data.source.rgbd_dir={rgbd}",
                              f"data.frames_per_fragment={FPF}", "data.fusion.tsdf_voxel=0.02", *extra])
    return OmegaConf.to_container(cfg.data, resolve=True)


def test_partial_release_reads_fuses_and_keeps_the_pairs_it_can(tmp_path):
    fragments, rgbd, bench = _fake_release(tmp_path)
    logs: list[str] = []
    root = prepare_dataset(_release_cfg(tmp_path / "out", fragments, rgbd, bench), log=logs.append)
    stats = read_manifest(root)["stats"]
    # fragment 3 lacks a frame: every pair with it is dropped; office has nothing and is left out
    assert stats["pairs"] == {"3DMatch": 3, "3DLoMatch": 0}
    assert stats["pairs_dropped"] == {"3DMatch": 5, "3DLoMatch": 4}
    assert stats["scenes"]["test"] == 1 and stats["fragments_read"] == 2 and stats["fragments_fused"] == 1
    assert any("3DMatch: 3 of 8 official pairs kept, 5 dropped" in m for m in logs)
    assert any("3DLoMatch: 0 of 4 official pairs kept, 4 dropped" in m for m in logs)
    lay = Layout(root)
    assert lay.scenes("test") == ["kitchen"]
    assert sorted(p.name for p in lay.benchmark_dir("3DMatch").iterdir()) == ["kitchen"]
    assert [(r.i, r.j) for r in read_gt_log(lay.benchmark_dir("3DMatch", "kitchen") / "gt.log")] == [(0, 1), (0, 2), (1, 2)]
    # fragments: .pth converted, .ply as given, 2 fused; .info.txt names each one's frames
    for k in (0, 1, 2):
        assert lay.fragment("kitchen", k).is_file()
        assert read_fragment_info(lay.fragment_info("kitchen", k)) == FragmentInfo("kitchen", "seq-01", FPF * k, FPF * k + 1)
    assert not lay.fragment("kitchen", 3).exists()
    np.testing.assert_allclose(read_cloud(lay.fragment("kitchen", 0))[0], read_cloud(fragments / "kitchen" / "cloud_bin_0.pth")[0])
    # the views of the fragments come from the linked RGB-D folder (jpg colour)
    ds = PairDataset(root, "3DMatch", n_views=2)
    s = ds[0]
    assert len(s.src_views) == 2 and s.src_views[0].color_path.endswith(".color.jpg")
    np.testing.assert_allclose(s.tgt_views[0].pose, np.eye(4), atol=1e-9)
    # the fused fragment lies where the given ones do: gt.log maps fragment 2 onto fragment 0
    from scipy.spatial import cKDTree

    p0 = read_cloud(lay.fragment("kitchen", 0))[0]
    p2 = read_cloud(lay.fragment("kitchen", 2))[0]
    T = ds.pairs[1].transform
    d, _ = cKDTree(p0).query(p2 @ T[:3, :3].T + T[:3, 3])
    assert np.median(d) < 0.02


def test_checks_leave_the_official_overlaps_and_gt_info_to_3dmatch(tmp_path, capsys):
    """pcrcg.data.checks on a release built by data=threedmatch: gt_overlap.log and gt.info are 3DMatch's (here
    made up: 0.5 and 100 I), so they are reported as not applicable rather than re-derived and failed; the
    poses are still checked against gt.log."""
    import json

    from pcrcg.data.checks import benchmark_writer, check_dataset, main

    fragments, rgbd, bench = _fake_release(tmp_path, missing_frame=None)  # every pair kept: both benchmarks
    root = prepare_dataset(_release_cfg(tmp_path / "out", fragments, rgbd, bench), log=lambda m: None)
    assert benchmark_writer(root) == "3DMatch's code"
    rep = check_dataset(root)
    assert rep.ok, rep.failed
    assert rep.not_applicable == [
        "benchmark overlaps (gt_overlap.log): not applicable: written by 3DMatch's code, not this project's",
        "gt.info: not applicable: written by 3DMatch's code, not this project's"]
    assert any(m.startswith("pose/gt agreement over 6 pairs") for m in rep.passed), rep.passed
    capsys.readouterr()
    assert main([str(root)]) == 0
    out = capsys.readouterr().out
    assert "n/a  gt.info: not applicable: written by 3DMatch's code, not this project's" in out and "FAIL" not in out
    # the same files with a manifest that says this project wrote them: re-derived, and the made-up values fail
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["params"]["name"] = "redkitchen"
    (root / "manifest.json").write_text(json.dumps(manifest))
    assert benchmark_writer(root) is None
    rep = check_dataset(root)
    assert rep.not_applicable == []
    assert [m.split(" ")[0] for m in rep.failed] == ["overlaps", "gt.info"], rep.failed


def test_partial_release_errors(tmp_path):
    fragments, rgbd, bench = _fake_release(tmp_path)
    # nothing can be built: no fragment file and no frames for the scenes of the benchmarks
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="no official pair has both fragments available"):
        prepare_dataset(_release_cfg(tmp_path / "out", empty, empty, bench), log=lambda m: None)
    assert not (tmp_path / "out").exists()
    # a pose that disagrees with gt.log: the frames are not the fragment's (named before fusing)
    write_matrix(rgbd / "kitchen" / "seq-01" / "frame-000004.pose.txt", make_transform(np.eye(3), [1.0, 0, 0]))
    with pytest.raises(DataError, match="frame-000004: pose disagrees with gt.log pair 0 2"):
        prepare_dataset(_release_cfg(tmp_path / "out", fragments, rgbd, bench), log=lambda m: None)
    # a truncated frame of a fragment to fuse
    write_matrix(rgbd / "kitchen" / "seq-01" / "frame-000004.pose.txt", _pose(4))
    jpg = rgbd / "kitchen" / "seq-01" / "frame-000005.color.jpg"
    jpg.write_bytes(jpg.read_bytes()[:100])
    with pytest.raises(DataError, match="frame-000005.color.jpg: JPEG is truncated"):
        prepare_dataset(_release_cfg(tmp_path / "out", fragments, rgbd, bench), log=lambda m: None)
    assert not (tmp_path / "out").exists()
    # a missing source folder is named
    with pytest.raises(DataError, match="nowhere: RGB-D folder"):
        prepare_dataset(_release_cfg(tmp_path / "out", fragments, tmp_path / "nowhere", bench), log=lambda m: None)


# --------------------------------------------------------------------------- the shared release


def _fusion_cfg():
    from omegaconf import OmegaConf

    return fusion_from(OmegaConf.to_container(compose("prepare", ["data=threedmatch"]).data, resolve=True))


@pytest.mark.shared
def test_fusing_frames_0_49_reproduces_the_release_cloud_bin_0():
    """3DMatch's fragment 0 of 7-scenes-redkitchen is frames 0-49 fused in frame 0's camera."""
    from scipy.spatial import cKDTree

    from pcrcg.data.fusion import fuse_frames
    from pcrcg.data.layout import read_depth, read_intrinsics, read_pose

    seq = shared_path("data", "real-rgbd", "7-scenes-redkitchen", "seq-01")
    ref, _ = read_cloud(shared_path("data", "real-3dmatch-fragments", "7-scenes-redkitchen", "cloud_bin_0.ply"))
    K = read_intrinsics(seq.parent / "camera-intrinsics.txt")
    colors, depths, poses = [], [], []
    for f in range(50):
        c, d, p = frame_paths(seq / f"frame-{f:06d}")
        colors.append(read_color(c))
        depths.append(read_depth(d))
        poses.append(read_pose(p))
    t0 = time.perf_counter()
    pts, _ = fuse_frames(colors, depths, poses, K, _fusion_cfg())
    seconds = time.perf_counter() - t0
    fused_to_ref = float(np.median(cKDTree(ref).query(pts)[0]))
    ref_to_fused = float(np.median(cKDTree(pts).query(ref)[0]))
    print(f"fused {len(pts)} points in {seconds:.1f} s; median NN distance fused->release {fused_to_ref * 1000:.1f} mm, "
          f"release->fused {ref_to_fused * 1000:.1f} mm")
    assert fused_to_ref < 0.01 and ref_to_fused < 0.01


@pytest.mark.slow
@pytest.mark.shared
def test_the_shared_partial_release_builds_27_and_10_pairs(tmp_path):
    fragments = shared_path("data", "real-3dmatch-fragments")
    rgbd = shared_path("data", "real-rgbd")
    bench = shared_path("data", "3dmatch-benchmarks")
    from omegaconf import OmegaConf

    cfg = compose("prepare", ["data=threedmatch", f"data.root={tmp_path / 'real'}", f"data.source.benchmarks_dir={bench}",
                              f"data.source.fragments_dir={fragments}", f"data.source.rgbd_dir={rgbd}"])
    root = prepare_dataset(OmegaConf.to_container(cfg.data, resolve=True), log=lambda m: None)
    stats = read_manifest(root)["stats"]
    assert stats["pairs"] == {"3DMatch": 27, "3DLoMatch": 10}
    assert stats["fragments_read"] == 6 and stats["fragments_fused"] == 4
    lay = Layout(root)
    assert lay.scenes("test") == ["7-scenes-redkitchen"]
    assert read_fragment_info(lay.fragment_info("7-scenes-redkitchen", 7)) == FragmentInfo(
        "7-scenes-redkitchen", "seq-01", 350, 399)
    views = load_views(lay, "7-scenes-redkitchen", 7, 3)
    assert [v.frame_id for v in views] == [350, 399, 374]


# --------------------------------------------------------------------------- colour camera != depth camera


def test_color_is_resampled_into_the_depth_camera():
    from pcrcg.data.layout import color_to_depth_camera

    Kd = np.array([[58.5, 0, 32], [0, 58.5, 24], [0, 0, 1]])
    Kc = np.array([[52.5, 0, 32], [0, 52.5, 24], [0, 0, 1]])  # wider colour camera, same centre
    u, v = np.meshgrid(np.arange(64), np.arange(48))
    # a colour image of a ray-direction pattern: pixel (u, v) of the colour camera sees direction d
    dx, dy = (u - 32) / 52.5, (v - 24) / 52.5
    color = np.stack([np.clip(128 + 300 * dx, 0, 255), np.clip(128 + 300 * dy, 0, 255), np.full_like(dx, 50)], -1)
    out = color_to_depth_camera(color.astype(np.uint8), Kc, Kd)
    # depth pixel (u, v) sees direction ((u - 32) / 58.5, ...): the warped colour there must encode it
    ex = np.clip(128 + 300 * (u - 32) / 58.5, 0, 255)
    inner = (np.abs(u - 32) < 25) & (np.abs(v - 24) < 18)
    assert np.abs(out[..., 0][inner].astype(float) - ex[inner]).max() <= 2.0
    assert np.array_equal(color_to_depth_camera(color.astype(np.uint8), Kd, Kd), color.astype(np.uint8))


def test_partial_release_records_an_unregistered_color_camera(tmp_path):
    from pcrcg.data.layout import color_camera, read_intrinsics

    fragments, rgbd, bench = _fake_release(tmp_path)
    extra = ['+data.source.color_intrinsics.kitch=[45.0,45.0,32.0,24.0]']
    root = prepare_dataset(_release_cfg(tmp_path / "out", fragments, rgbd, bench, *extra), log=lambda m: None)
    lay = Layout(root)
    Kc = color_camera(lay, "kitchen", read_intrinsics(lay.intrinsics("kitchen")))
    assert Kc is not None and Kc[0, 0] == 45.0
    assert not (rgbd / "kitchen" / "camera-intrinsics-color.txt").exists()  # the release's folder is untouched
    s = PairDataset(root, "3DMatch", n_views=1)[0]
    from pcrcg.data.layout import color_to_depth_camera, read_color

    raw = read_color(s.src_views[0].color_path)
    assert np.array_equal(s.src_views[0].color, color_to_depth_camera(raw, Kc, K))
    assert not np.array_equal(s.src_views[0].color, raw)
    with pytest.raises(ConfigError, match="data.source.color_intrinsics.kitch"):
        prepare_dataset(_release_cfg(tmp_path / "out2", fragments, rgbd, bench,
                                     '+data.source.color_intrinsics.kitch=[0,45.0,32.0,24.0]'), log=lambda m: None)
