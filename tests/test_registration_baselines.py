"""Classical baselines: FPFH + RANSAC, ICP, colored ICP, SIFT-DLT (pcrcg.registration.baselines)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pcrcg.data.dataset import View
from pcrcg.evaluation.metrics import information_matrix, registration_error, rotation_error_deg
from pcrcg.geometry import axis_angle_to_matrix, invert, make_transform, project, transform_points
from pcrcg.registration import BaselineConfig, lift_pixels, register_pair
from pcrcg.testing.pairs import make_fragment_pair
from pcrcg.testing.rooms import box_room

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FRAMES = SHARED / "data" / "real-rgbd" / "redkitchen-frames"


def _err(T_est, T):
    return rotation_error_deg(T_est[:3, :3], T[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T[:3, 3]))


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(0)
    pts, cols = box_room(rng, 30000)
    return make_fragment_pair(rng, pts, cols, crop=0.2, voxel=0.04)


def test_fpfh_ransac_registers_a_room_pair(pair):
    res = register_pair("fpfh", pair.src_points, pair.tgt_points, seed=0)
    r, t = _err(res.transform, pair.transform)
    assert r < 10.0 and t < 0.3  # coarse (7.5 cm threshold, no refinement) but right
    info = information_matrix(pair.src_points[pair.src_overlap])
    assert registration_error(res.transform, pair.transform, info) <= 0.2**2  # registered by the protocol
    assert res.src_corr is not None and len(res.src_corr) == res.info["n_correspondences"] > 10


def test_icp_converges_from_a_nearby_estimate_and_not_from_far(pair):
    D = make_transform(axis_angle_to_matrix([0.3, 1, 0.2], np.radians(3)), [0.03, -0.02, 0.02])
    init = pair.transform @ D
    res = register_pair("icp", pair.src_points, pair.tgt_points, init=init)
    r, t = _err(res.transform, pair.transform)
    r0, t0 = _err(init, pair.transform)
    assert r < 0.5 * r0 and t < 0.02
    # the pair is in random frames: from the identity, point-to-plane ICP cannot find it
    r_id, _ = _err(register_pair("icp", pair.src_points, pair.tgt_points).transform, pair.transform)
    assert r_id > 10.0


def test_color_icp_refines_and_needs_colors(pair):
    D = make_transform(axis_angle_to_matrix([1, 0, 0.4], np.radians(2)), [0.02, 0.01, -0.02])
    init = pair.transform @ D
    res = register_pair("color_icp", pair.src_points, pair.tgt_points, src_colors=pair.src_colors,
                        tgt_colors=pair.tgt_colors, init=init)
    r, t = _err(res.transform, pair.transform)
    assert r < 1.0 and t < 0.02
    with pytest.raises(ValueError, match="colors"):
        register_pair("color_icp", pair.src_points, pair.tgt_points, init=init)


# --------------------------------------------------------------------------- SIFT: lifted (and SIFT-DLT, test_paper_fidelity)


def _plane_view(pose_cam_to_frag: np.ndarray, plane=(np.array([0.2, 0.1, 1.0]), 2.0), H=120, W=160) -> View:
    """A camera (pose camera-to-fragment) looking at the plane ``n.p = d`` given in the fragment frame;
    depth is exact per pixel centre (0 in the top band and where the plane is behind)."""
    K = np.array([[150.0, 0, W / 2 - 0.5], [0, 150.0, H / 2 - 0.5], [0, 0, 1]])
    n, d = plane
    R, t = pose_cam_to_frag[:3, :3], pose_cam_to_frag[:3, 3]
    n_c, d_c = R.T @ n, d - n @ t  # the plane in camera coordinates
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1)
    z = d_c / (rays @ n_c)
    depth = np.where((z > 0.1) & (z < 6.0), z, 0.0).astype(np.float32)
    depth[:5] = 0.0  # a band without depth
    return View(np.zeros((H, W, 3), np.uint8), depth, K, pose_cam_to_frag, 0, "synthetic.png")


def test_lift_pixels_back_projects_through_the_pose():
    pose = make_transform(axis_angle_to_matrix([0, 1, 0], 0.3), [0.1, 0.2, 0.3])
    v = _plane_view(pose)
    uv = np.array([[10.0, 50.0], [80.0, 60.0], [20.0, 2.0], [500.0, 10.0]])  # valid, valid, no depth, outside
    pts, ok = lift_pixels(uv, v)
    assert ok.tolist() == [True, True, False, False]
    cam = transform_points(invert(pose), pts[ok])
    back, z = project(cam, v.intrinsics)
    assert np.allclose(back, uv[ok], atol=1e-9)
    assert np.allclose(z, v.depth[uv[ok, 1].astype(int), uv[ok, 0].astype(int)], atol=1e-6)


def test_sift_lifted_with_a_monkeypatched_matcher(monkeypatch):
    """Matches generated from a known relative pose (plus outliers) through the matcher's API."""
    from pcrcg.vision import matching as vm

    rng = np.random.default_rng(1)
    T = make_transform(axis_angle_to_matrix([0.2, 1.0, 0.1], 0.4), [0.5, -0.1, 0.2])  # src frag -> tgt frag
    n, d = np.array([0.2, 0.1, 1.0]), 2.0  # the scene: a plane in the source fragment's frame
    src_view = _plane_view(np.eye(4), (n, d))
    tgt_pose = make_transform(axis_angle_to_matrix([1, 0, 0], 0.05), [0.0, 0.05, 0.0])  # camera -> tgt fragment
    nt = T[:3, :3] @ n  # the same plane in the target fragment's frame
    tgt_view = _plane_view(tgt_pose, (nt, d + nt @ T[:3, 3]))

    def fake_match(img_a, img_b, cfg=None):
        uv_a = rng.uniform([0, 10], [159, 119], size=(300, 2))
        pa, ok = lift_pixels(uv_a, src_view)
        p_tgt_cam = transform_points(invert(tgt_view.pose), transform_points(T, pa[ok]))
        uv_b, _ = project(p_tgt_cam, tgt_view.intrinsics)
        uv_b = uv_b + rng.normal(scale=0.3, size=uv_b.shape)
        uv_b[: len(uv_b) // 3] = rng.uniform([0, 10], [159, 119], size=(len(uv_b) // 3, 2))  # outliers
        return vm.Matches(uv_a[ok], uv_b, np.ones(len(uv_b), np.float32))

    monkeypatch.setattr(vm, "match_images", fake_match)
    res = register_pair("sift_lifted", None, None, src_views=[src_view], tgt_views=[tgt_view], seed=0)
    r, t = _err(res.transform, T)
    # depth is read at the nearest pixel of a slanted plane: a few mm of lifting noise
    assert r < 1.0 and t < 0.03
    assert res.info["n_correspondences"] > 100
    with pytest.raises(ValueError, match="views"):
        register_pair("sift_lifted", None, None, src_views=[], tgt_views=[tgt_view])


def test_sift_lifted_on_real_kinect_frames():
    """Real SIFT matches (pcrcg.vision.matching) between two real RGB-D frames; truth from poses."""
    if not FRAMES.is_dir():
        pytest.skip(f"{FRAMES} is not available")
    from pcrcg.data.layout import read_color, read_depth, read_intrinsics, read_pose

    K = read_intrinsics(FRAMES / "camera-intrinsics.txt")

    def view(k: int, ref: int) -> View:
        """Frame k as a view of the fragment whose frame is the camera of frame ``ref``."""
        pose = invert(read_pose(FRAMES / f"frame-{ref:06d}.pose.txt")) @ read_pose(FRAMES / f"frame-{k:06d}.pose.txt")
        color = FRAMES / f"frame-{k:06d}.color.png"
        return View(read_color(color), read_depth(FRAMES / f"frame-{k:06d}.depth.png"), K, pose, k, str(color))

    # fragment A = camera of frame 8, fragment B = camera of frame 40
    src, tgt = view(8, 8), view(40, 40)
    Pa, Pb = read_pose(FRAMES / "frame-000008.pose.txt"), read_pose(FRAMES / "frame-000040.pose.txt")
    T = invert(Pb) @ Pa  # A -> B
    cfg = BaselineConfig.from_dict({"sift_lifted": {"matcher": {"method": "sift", "max_keypoints": 1500}}})
    res = register_pair("sift_lifted", None, None, src_views=[src], tgt_views=[tgt], cfg=cfg, seed=0)
    r, t = _err(res.transform, T)
    assert r < 2.0 and t < 0.05
