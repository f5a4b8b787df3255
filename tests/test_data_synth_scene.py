"""The generator's rooms, furniture and camera effects alone (generator v4)."""

from __future__ import annotations

import numpy as np
import pytest

from pcrcg.data.synth import furniture as F
from pcrcg.data.synth.images import image_bank
from pcrcg.data.synth.panel import Panel, Room
from pcrcg.data.synth.render import RoomRenderer, SensorModel, motion_blur
from pcrcg.data.synth.scene import ROOM_TYPES, make_room
from pcrcg.data.synth.shapes import box, ellipsoid, frustum, placement
from pcrcg.data.synth.textures import Texture
from pcrcg.data.synthmatch import auto_exposure
from pcrcg.geometry import look_at

K = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])
GREY = Texture("plain", np.array([[0.5, 0.5, 0.5]] * 3), grain=0.0)
SKY = Texture("plain", np.array([[0.9, 0.9, 0.9]] * 3), grain=0.0)  # as bright as scene._sky's


def _vertices(panels: list[Panel]) -> np.ndarray:
    return np.concatenate([np.stack([p.origin, p.origin + p.axis_u, p.origin + p.axis_v]) for p in panels])


def test_shapes_are_placed_and_closed():
    M = placement(1.0, 2.0, 0.0, yaw=0.7)
    v = _vertices(box(M, (0.4, 0.2, 0.5), GREY, "x"))
    np.testing.assert_allclose(v.mean(0)[:2], [1.0, 2.0], atol=0.15)
    assert v[:, 2].min() == pytest.approx(0.0) and v[:, 2].max() == pytest.approx(0.5)
    cyl = frustum(np.eye(4), 0.1, 0.1, 0.3, 12, GREY, "x")
    r = np.linalg.norm(_vertices(cyl)[:, :2], axis=1)
    assert r.max() == pytest.approx(0.1) and all(p.tri for p in cyl)
    ell = _vertices(ellipsoid(np.eye(4), (0.2, 0.1, 0.05), 6, 12, GREY, "x"))
    q = (ell / np.array([0.2, 0.1, 0.05])) ** 2
    np.testing.assert_allclose(q.sum(1), 1.0, atol=1e-9)  # every vertex on the surface


@pytest.mark.parametrize("make", [F.chair, F.table, F.desk, F.sofa, F.bed, F.bookshelf, F.cabinet, F.fridge,
                                  F.lamp, F.plant, F.bin_, F.carton, F.bottle, F.mug, F.papers])
def test_furniture_is_made_of_parts_of_real_size(make):
    rng = np.random.default_rng(4)
    it = make(rng, np.eye(4))
    v = _vertices(it.panels)
    assert len(it.panels) >= 5
    assert v[:, 2].min() > -0.02  # stands on the floor
    w, d, h = it.size
    assert 0.01 <= h <= 2.2 and 0.02 <= max(w, d) <= 2.3
    assert np.ptp(v[:, 2]) <= h + 0.35


def test_a_chair_has_legs_a_seat_and_a_back():
    # a four-legged chair (seed chosen so it is not the office chair): parts at three heights
    for seed in range(10):
        rng = np.random.default_rng(seed)
        it = F.chair(rng, np.eye(4))
        tops = sorted({round(float(p.origin[2] + max(p.axis_u[2], 0) + max(p.axis_v[2], 0)), 2) for p in it.panels})
        if len(it.panels) < 60:
            break
    assert len(tops) >= 3 and tops[-1] > 0.7  # legs, seat, back above the seat


def test_rooms_vary_like_real_ones():
    kinds, shapes, doors, windows, n = set(), set(), 0, 0, 12
    for seed in range(n):
        room = make_room(np.random.default_rng(seed))
        kinds.add(room.room_type)
        floors = [p for p in room.panels if p.kind == "floor"]
        shapes.add(len(floors))  # one rectangle: a box; more: L-shapes, alcoves, doorways
        windows += any(p.kind == "sky" for p in room.panels)
        doors += len(floors) > 1
        assert 800 < len(room.panels) < 20000
        assert room.walkable is not None and room.walkable.sum() * room.cell**2 > 1.0  # m^2 to walk
        yaws = {round(float(np.degrees(np.arctan2(p.axis_u[1], p.axis_u[0]))) % 90) for p in room.panels
                if p.kind == "furniture" and abs(p.axis_u[2]) < 1e-6 and np.linalg.norm(p.axis_u) > 0.2}
        assert len(yaws) >= 3  # furniture at other angles than the room's axes
    assert kinds <= set(ROOM_TYPES) and len(kinds) >= 4
    assert len(shapes) >= 2 and windows >= 3 and doors >= 3
    with pytest.raises(ValueError):
        make_room(np.random.default_rng(0), room_type="garage") if False else F.material  # noqa: B018
        from pcrcg.data.synth.textures import material
        material(np.random.default_rng(0), "garage")


def test_image_bank_ships_with_the_install():
    bank = image_bank()
    assert len(bank) >= 8
    for img in bank:
        assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.float32
        assert 0 <= img.min() and img.max() <= 1 and img.std() > 0.05


def _wall_room(tex: Texture) -> Room:
    X, Y, Z = np.eye(3)
    room = Room(size=np.array([4.0, 4.0, 3.0]))
    room.panels = [Panel(np.array([4.0, 0, 0]), Y * 4, Z * 3, tex, "wall"),
                   Panel(np.array([3.9, 1.5, 1.0]), Y * 1.0, Z * 1.0, SKY, "sky")]
    room.lights = np.array([[2.0, 2.0, 2.8]])
    room.light_power = np.array([2.0])
    return room


def test_windows_glow_and_have_no_depth():
    room = _wall_room(GREY)
    r = RoomRenderer(room, SensorModel(dropout=0.0, edge_drop=0.0, noise_scale=0.0))
    rad = r.radiance(look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5]), K, 80, 60)
    sky = rad.linear.mean(2) > 1.0
    assert sky.sum() > 50
    assert np.all(rad.depth[sky] == 0) and np.all(rad.depth[~sky & (rad.linear.mean(2) > 0)] > 0)


def test_dark_surfaces_lose_depth():
    black = Texture("plain", np.array([[0.01, 0.01, 0.01]] * 3), grain=0.0)
    P = look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5])
    holes = []
    for tex in (GREY, black):
        r = RoomRenderer(_wall_room(tex), SensorModel(dropout=0.0, edge_drop=0.0, dark_drop=0.7))
        rad = r.radiance(P, K, 80, 60)
        d = r.sensor_depth(rad, np.random.default_rng(0))
        holes.append((d[rad.valid] == 0).mean())
    assert holes[1] > holes[0] + 0.4


def test_motion_blur_smears_along_the_motion_only():
    img = np.zeros((40, 40, 1), np.float32)
    img[20, 20] = 1.0
    out = motion_blur(img, np.array([8.0, 0.0]))[:, :, None] if motion_blur(img, np.array([8.0, 0.0])).ndim == 2 \
        else motion_blur(img, np.array([8.0, 0.0]))
    row = out[20, :, 0]
    assert (row > 0).sum() >= 7 and out[:, 20, 0][np.arange(40) != 20].max() == 0
    assert out.sum() == pytest.approx(1.0, rel=1e-5)
    assert motion_blur(img, np.array([0.2, 0.1])) is img  # below a pixel: unchanged


def test_image_motion_follows_the_camera():
    room = _wall_room(GREY)
    r = RoomRenderer(room)
    P0 = look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5])
    P1 = look_at([2.0, 2.05, 1.5], [4.0, 2.05, 1.5])  # 5 cm to the left (+y)
    rad = r.radiance(P0, K, 80, 60)
    m = r.image_motion(P0, P1, K, rad.depth)
    # the wall 2 m away moves right in the image by f * 0.05 / 2 = 2.5 px
    assert m[0] == pytest.approx(2.5, abs=0.3) and abs(m[1]) < 0.3


def test_auto_exposure_adapts_with_lag():
    dark, bright = np.full((10, 10, 3), 0.05, np.float32), np.full((10, 10, 3), 0.5, np.float32)
    g = auto_exposure(None, dark, 1 / 30)
    assert g * 0.05 == pytest.approx(0.18, rel=0.01)
    g1 = auto_exposure(g, bright, 1 / 30)  # one frame later: still too bright
    assert g1 * 0.5 > 0.3
    for _ in range(60):  # two seconds: settled
        g1 = auto_exposure(g1, bright, 1 / 30)
    assert g1 * 0.5 == pytest.approx(0.18, rel=0.05)


def test_sensor_jpeg_and_noise_change_the_image_but_not_its_level():
    room = _wall_room(Texture("checks", np.array([[0.8, 0.2, 0.2], [0.2, 0.2, 0.8], [0.5] * 3]), 0.2, grain=0.0))
    P = look_at([2.0, 2.0, 1.5], [4.0, 2.0, 1.5])
    clean = RoomRenderer(room, SensorModel(color_noise=0.0)).render(P, K, 80, 60, np.random.default_rng(0))[0]
    real = RoomRenderer(room, SensorModel(shot_noise=0.002, jpeg_quality=80, vignetting=0.3)).render(
        P, K, 80, 60, np.random.default_rng(0))[0]
    assert np.abs(clean.astype(int) - real.astype(int)).mean() > 1.0
    assert abs(clean.mean() - real.mean()) < 20
    corner, centre = real[:8, :8].mean(), real[26:34, 36:44].mean()
    assert corner < centre  # vignetting


def test_textures_are_srgb_colours_lit_in_linear_light():
    room = _wall_room(GREY)
    room.lights, room.light_power, room.ambient = np.zeros((0, 3)), np.zeros(0), 0.3
    rad = RoomRenderer(room, SensorModel(dropout=0.0, edge_drop=0.0, noise_scale=0.0)).radiance(
        look_at([2.0, 2.0, 1.5], [4.0, 0.5, 1.5]), K, 80, 60)
    wall = rad.valid & (rad.linear.mean(2) < 1.0)
    assert wall.sum() > 100
    # a printed 50% grey reflects 0.5 ** 2.2 = 21.8% of the light (v4 lit the sRGB value: 50%)
    assert np.allclose(rad.linear[wall], 0.3 * 0.5**2.2, rtol=1e-4)
    assert np.allclose(rad.albedo[wall], 0.5, atol=1e-6)  # holes on dark surfaces: the printed value
