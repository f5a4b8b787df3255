"""Stages of the generator alone, on tiny data made here: textures, rendering, fusion, pairs."""

from __future__ import annotations

import numpy as np
import pytest

from pcrcg.data.fusion import FusionConfig, fuse_frames
from pcrcg.data.pairs import info_from_points, info_matrix, overlap_ratio, voxel_downsample
from pcrcg.data.synth.camera import ScanConfig, ScanPath, camera_path
from pcrcg.data.synth.render import RoomRenderer, SensorModel
from pcrcg.data.synth.scene import Panel, Room, make_room
from pcrcg.data.synth.textures import FAMILIES, Texture, image_texture, random_texture
from pcrcg.evaluation.metrics import information_matrix
from pcrcg.geometry import invert, look_at, make_transform, random_rotation, skew, transform_points

K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])


def _box_room(tex=None) -> Room:
    """A 4 x 4 x 3 m room with plain walls and one light; no furniture."""
    X, Y, Z = np.eye(3)
    tex = tex or Texture("plain", np.array([[0.5, 0.5, 0.5]] * 3), grain=0.0)
    W, D, H = 4.0, 4.0, 3.0
    room = Room(size=np.array([W, D, H]))
    room.panels = [
        Panel(np.zeros(3), X * W, Y * D, tex, "floor"),
        Panel(np.array([0, D, H]), X * W, -Y * D, tex, "ceiling"),
        Panel(np.array([0, 0, 0]), Z * H, X * W, tex, "wall"),
        Panel(np.array([W, D, 0]), Z * H, -X * W, tex, "wall"),
        Panel(np.array([0, D, 0]), Z * H, -Y * D, tex, "wall"),
        Panel(np.array([W, 0, 0]), Z * H, Y * D, tex, "wall"),
    ]
    room.lights = np.array([[2.0, 2.0, 2.8]])
    room.light_power = np.array([2.0])
    return room


@pytest.mark.parametrize("family", FAMILIES)
def test_textures_deterministic_in_range_and_varied(family):
    rng = np.random.default_rng(3)
    if family == "image":
        tex = image_texture(rng, (1.0, 1.0))
    else:
        tex = random_texture(rng, "poster")
        tex.family = family
    u, v = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 64))
    a = tex(u.ravel(), v.ravel())
    b = tex(u.ravel(), v.ravel())
    assert a.shape == (64 * 64, 3)
    np.testing.assert_array_equal(a, b)
    assert a.min() >= 0 and a.max() <= 1
    if family != "plain":
        assert a.std(axis=0).max() > 0.03  # a pattern, not a flat color


def test_render_depth_is_the_true_distance():
    room = _box_room()
    # camera at the room centre, 1.5 m high, looking straight at the wall x = 4 (2 m away)
    pose = look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5])
    r = RoomRenderer(room, SensorModel(noise_scale=0.0, dropout=0.0, edge_drop=0.0))
    color, depth, clean = r.render(pose, K, 80, 60, np.random.default_rng(0))
    assert color.shape == (60, 80, 3) and color.dtype == np.uint8
    # the optical axis hits the wall at z = 2; all wall pixels have z = 2 (fronto-parallel)
    assert clean[29, 40] == pytest.approx(2.0, abs=1e-4)
    wall = np.abs(clean - 2.0) < 1e-3
    assert wall.mean() > 0.9
    np.testing.assert_allclose(depth[wall], 2.0, atol=1e-4)  # noise off


def test_depth_noise_grows_with_distance_and_range_limits():
    room = _box_room()
    rng = np.random.default_rng(1)
    r = RoomRenderer(room, SensorModel(dropout=0.0, edge_drop=0.0, max_depth=3.6))
    stds = []
    for dist in (1.0, 3.0):
        pose = look_at([4.0 - dist, 2.0, 1.5], [4.0, 2.0, 1.5])
        _, depth, clean = r.render(pose, K, 80, 60, rng)
        m = (depth > 0) & (np.abs(clean - dist) < 1e-3)
        stds.append(float(np.std(depth[m] - clean[m])))
    expected = [0.0012 + 0.0019 * (d - 0.4) ** 2 for d in (1.0, 3.0)]
    assert stds[0] == pytest.approx(expected[0], rel=0.2)
    assert stds[1] == pytest.approx(expected[1], rel=0.2)
    # beyond max_depth there is no depth
    pose = look_at([0.2, 2.0, 1.5], [4.0, 2.0, 1.5])
    _, depth, clean = r.render(pose, K, 80, 60, rng)
    assert np.all(depth[clean > 3.6] == 0)


def test_grazing_surfaces_get_holes():
    room = _box_room()
    r = RoomRenderer(room, SensorModel(dropout=0.0, edge_drop=0.0, noise_scale=0.0, min_depth=0.05))
    # look along the wall y = 0 from 15 cm beside it; the wall is on the image's right (camera x = -y)
    pose = look_at([0.5, 0.15, 1.5], [3.5, 0.15, 1.5])
    _, depth, clean = r.render(pose, K, 80, 60, np.random.default_rng(0))
    x_cam = (np.arange(80) - K[0, 2]) / K[0, 0]
    cos_inc = x_cam / np.sqrt(1 + x_cam**2)  # incidence on the wall y = 0 for columns that hit it
    hits_wall = (x_cam > 0.15 / 3.5) & (clean > 0).all(0)
    grazing = hits_wall & (cos_inc < 0.12)
    steep = hits_wall & (cos_inc > 0.3)
    assert grazing.sum() >= 3 and steep.sum() >= 3
    assert np.all(depth[:, grazing] == 0)
    assert np.all(depth[:, steep] > 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_path_moves_at_hand_held_speeds_inside_the_free_space(seed):
    rng = np.random.default_rng(seed)
    room = make_room(rng)
    dt = 1 / 30
    poses = camera_path(room, 600, dt, rng)  # 20 s at 30 fps
    pos = poses[:, :3, 3]
    assert np.all(pos[:, :2] > 0.3) and np.all(pos[:, 0] < room.size[0] - 0.3) and np.all(pos[:, 1] < room.size[1] - 0.3)
    # mostly over the free floor (the loop may pass over low tables, never through shelves or walls)
    assert room.is_walkable(pos[:, :2]).mean() > 0.7
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) / dt
    assert np.median(speed) < 0.5 and speed.max() < 1.5  # m/s: a slow walk with moments of a brisk one, not a throw
    fwd = poses[:, :3, 2]
    turn = np.degrees(np.arccos(np.clip(np.sum(fwd[1:] * fwd[:-1], 1), -1, 1))) / dt
    assert 3 < np.median(turn) < 45 and turn.max() < 120  # deg/s of a hand-held scan
    assert np.all(pos[:, 2] > 1.0) and np.all(pos[:, 2] < 1.9)
    tilt = np.degrees(np.arcsin(fwd[:, 2]))
    assert np.median(tilt) < -10  # looking down at tables and floor
    rolls = poses[:, :3, 0][:, 2]  # the image x axis leaves the horizontal: the hand rolls
    assert np.abs(rolls).max() > 0.01
    for P in poses[::50]:
        R = P[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_sweeping_scan_goes_back_and_forth_over_an_arc(seed):
    """sweep_deg: the loop angle swings +-sweep_deg about a middle that drifts at drift_deg_s, so the
    operator passes over the same part of the room again and again; 0 goes round (v5)."""
    room = make_room(np.random.default_rng(seed))
    t = np.arange(0, 66.7, 1 / 30)
    sweep = ScanPath(room, np.random.default_rng(seed), ScanConfig(turn_rate_deg=10, sweep_deg=60, drift_deg_s=2))
    loop = ScanPath(room, np.random.default_rng(seed), ScanConfig(turn_rate_deg=10, sweep_deg=0))
    th = sweep._theta(t)
    middle = sweep.theta0 + sweep.direction * np.radians(2.0) * t
    off = np.degrees(th - middle)
    assert np.abs(off).max() <= 60 + 1e-9 and np.abs(off).max() > 45  # the whole arc is swept
    turns = np.sum(np.diff(np.sign(np.diff(th))) != 0)
    assert turns >= 2  # back, forth and back again in a 40-fragment scan
    assert np.all(np.diff(loop._theta(t)) * loop.direction > 0)  # v5: round and round, never back
    # the same hand: speed along the arc never beyond the loop's, and the sweep keeps the heading's range
    assert np.abs(np.diff(th - middle)).max() <= np.abs(np.diff(loop._theta(t))).max() + 1e-12
    poses = sweep.pose(t[::10])
    assert np.all(np.isfinite(poses)) and room.is_walkable(poses[:, :2, 3]).mean() > 0.7


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_an_inward_scan_stands_its_radius_from_the_table_and_tilts_by_inward_tilt(seed):
    """Generator v7: inward scans circle the table's middle at ``inward_radius`` (at most 80% of the
    free floor's reach) with ``inward_tilt_deg`` more tilt than outward ones."""
    room = make_room(np.random.default_rng(seed))
    assert room.focus is not None  # these seeds draw rooms with a central table
    t = np.arange(0, 20.0, 0.5)
    far = ScanPath(room, np.random.default_rng(seed), ScanConfig(inward_share=1.0, inward_radius=(2.0, 2.0)))
    near = ScanPath(room, np.random.default_rng(seed), ScanConfig(inward_share=1.0, inward_radius=(1.0, 1.0),
                                                                  inward_tilt_deg=10.0))
    assert far.inward and near.inward
    # both are min(80% of the free reach, radius) per direction
    assert far.reach.max() == pytest.approx(2.0) and near.reach.max() == pytest.approx(1.0)
    np.testing.assert_allclose(near.reach, np.minimum(far.reach, 1.0))
    pf, pn = far.pose(t), near.pose(t)
    d_far = np.linalg.norm(pf[:, :2, 3] - room.focus, axis=1)
    d_near = np.linalg.norm(pn[:, :2, 3] - room.focus, axis=1)
    assert np.all(np.abs(d_far - far._radius(far._theta(t))) < 0.3)  # the loop plus the hand's wobble
    assert np.median(d_far) > np.median(d_near)
    tilt_far = np.degrees(np.arcsin(pf[:, 2, 2]))
    tilt_near = np.degrees(np.arcsin(pn[:, 2, 2]))
    np.testing.assert_allclose(tilt_far - tilt_near, 10.0, atol=1e-6)  # the same hand, 10 deg less tilt


def test_fusion_of_a_plane_lies_on_the_plane():
    room = _box_room(Texture("checks", np.array([[0.9, 0.1, 0.1], [0.1, 0.1, 0.9], [0.5, 0.5, 0.5]]), 0.25, grain=0.0))
    r = RoomRenderer(room, SensorModel(dropout=0.0, edge_drop=0.0))
    rng = np.random.default_rng(0)
    poses = [look_at([2.0 + 0.05 * k, 2.0, 1.5], [4.0, 2.0 + 0.05 * k, 1.5]) for k in range(4)]
    frames = [r.render(P, K, 80, 60, rng) for P in poses]
    pts, cols = fuse_frames([f[0] for f in frames], [f[1] for f in frames], poses, K,
                            FusionConfig(tsdf_voxel=0.02, fragment_voxel=0.0, depth_max=4.5))
    assert len(pts) > 500
    world = transform_points(poses[0], pts.astype(np.float64))  # fragment frame = first camera
    on_wall = np.abs(world[:, 0] - 4.0) < 0.05
    assert on_wall.mean() > 0.8
    assert np.median(np.abs(world[on_wall, 0] - 4.0)) < 0.01
    # colours come through: the red and blue checks are both present
    assert (cols[on_wall][:, 0] > 0.5).mean() > 0.2 and (cols[on_wall][:, 2] > 0.5).mean() > 0.2


def test_fusion_returns_points_from_a_single_frame():
    # Open3D's VoxelBlockGrid drops everything below its default weight threshold of 3
    room = _box_room()
    r = RoomRenderer(room)
    P = look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5])
    c, d, _ = r.render(P, K, 80, 60, np.random.default_rng(0))
    pts, _ = fuse_frames([c], [d], [P], K, FusionConfig(tsdf_voxel=0.03))
    assert len(pts) > 100


def test_overlap_ratio_known_cases():
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0], indexing="ij"), -1).reshape(-1, 3) * 0.02
    T = make_transform(random_rotation(rng), rng.normal(size=3))
    moved = transform_points(invert(T), g)  # "fragment j", mapped into i by T
    assert overlap_ratio(g, moved, T) == pytest.approx(1.0)
    half = g[g[:, 0] < 0.39]  # the first 20 of 40 rows
    assert overlap_ratio(g, transform_points(invert(T), half), T) == pytest.approx(1.0)  # max of both directions
    assert overlap_ratio(half, transform_points(invert(T), g), T) == pytest.approx(1.0)
    far = transform_points(invert(T), g + [5, 0, 0])
    assert overlap_ratio(g, far, T) == 0.0
    shifted = transform_points(invert(T), g + [0.4, 0, 0])  # 20 rows coincide, 1 more is 2 cm < 3.75 cm away
    assert overlap_ratio(g, shifted, T) == pytest.approx(21 / 40)


def test_info_matrix_formula():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(7, 3))
    expected = np.zeros((6, 6))
    for q in p:
        G = np.hstack([np.eye(3), -skew(q)])
        expected += G.T @ G
    np.testing.assert_allclose(info_from_points(p), expected)
    # translation-first convention: info[0:3,0:3] = n I and info[0,4] = sum z (as the official files)
    assert expected[0, 0] == 7 and expected[0, 4] == pytest.approx(p[:, 2].sum())
    # capped at 5000 correspondences like the official files' info[0,0]
    g = rng.uniform(size=(8000, 3))
    M = info_matrix(g, g, np.eye(4))
    assert M[0, 0] == 5000


def test_info_matrix_agrees_with_the_evaluations_independent_one():
    """The data code's information matrix (G^T G summed) and the evaluation's (closed form from the
    point sums) are two implementations on purpose (pcrcg.data.checks checks one with the other);
    they give the same matrix."""
    p = np.random.default_rng(3).uniform(-2, 2, size=(500, 3)) + [0.5, -1.0, 3.0]
    np.testing.assert_allclose(info_from_points(p), information_matrix(p), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(info_from_points(np.zeros((0, 3))), information_matrix(np.zeros((0, 3))))


def test_info_matrix_quadratic_form_is_the_protocol_error():
    """e^T info e = sum ||t + q_xyz x p||^2 exactly for e = [t, q_xyz]: the 3DMatch RMSE proxy.

    (With q_xyz ~ half the rotation vector, this proxy weighs rotation half as much as the true
    displacement; that is the official protocol and we keep it.)"""
    rng = np.random.default_rng(2)
    p = rng.uniform(-1, 1, size=(300, 3)) + [0, 0, 2]
    M = info_from_points(p)
    t, q = rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.01
    e = np.concatenate([t, q])
    assert e @ M @ e == pytest.approx(np.sum(np.linalg.norm(t + np.cross(q, p), axis=1) ** 2), rel=1e-10)


def test_voxel_downsample_averages():
    pts = np.array([[0.001, 0.001, 0.001], [0.003, 0.003, 0.003], [0.5, 0.5, 0.5]])
    out = voxel_downsample(pts, 0.01)
    assert len(out) == 2
    np.testing.assert_allclose(out[0], [0.002, 0.002, 0.002])
