"""KPConv in plain PyTorch: kernel disposition, the convolution against a naive loop, the CPU
pipeline (grid subsampling, radius neighbours, pyramids, stacking) and the neighbour cache."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.geometry import make_transform, random_rotation
from pcrcg.models.kpconv import (
    KPConv,
    PyramidCache,
    PyramidSpec,
    build_pyramid,
    calibrate_limits,
    grid_subsample,
    kernel_points,
    kpconv,
    radius_neighbors,
    stack_pair,
)
from pcrcg.models.kpconv.ops import nearest_neighbor, radius_pairs
from pcrcg.testing.rooms import box_room


def test_kernel_disposition_is_deterministic_and_well_spread():
    k = kernel_points(15, radius=1.0, seed=0)
    assert k.shape == (15, 3) and k.dtype == np.float32
    np.testing.assert_array_equal(k[0], 0.0)  # fixed centre point
    r = np.linalg.norm(k[1:], axis=1)
    assert abs(r.mean() - 0.66) < 1e-5  # KPConv's mean radius ratio
    assert r.max() < 0.8 and r.min() > 0.5  # a shell around the centre
    d = np.linalg.norm(k[:, None] - k[None], axis=-1) + np.eye(15) * 9
    assert d.min() > 0.45  # no two kernel points crowd together
    np.testing.assert_array_equal(k, kernel_points(15, 1.0, 0))
    np.testing.assert_allclose(kernel_points(15, 2.5, 0), 2.5 * k, rtol=1e-6)


def naive_kpconv(q, s, nb, x, kernel, w, extent, normalize=True):
    """One query, one neighbour, one kernel point at a time."""
    out = np.zeros((len(q), w.shape[2]))
    for i in range(len(q)):
        count = 0
        for j in nb[i]:
            if j == len(s):
                continue
            count += 1
            for k in range(len(kernel)):
                d = np.linalg.norm(s[j] - q[i] - kernel[k])
                h = max(0.0, 1.0 - d / extent)
                out[i] += h * (x[j] @ w[k])
        if normalize:
            out[i] /= max(count, 1)
    return out


@pytest.mark.parametrize("normalize", [True, False])
def test_kpconv_matches_naive_loop(normalize):
    rng = np.random.default_rng(1)
    s = rng.uniform(0, 1, (40, 3))
    q = s[::3] + rng.normal(0, 0.01, (len(s[::3]), 3))
    nb = radius_neighbors(q, s, 0.35, 12)
    assert (nb == len(s)).any()  # some shadow padding is exercised
    x = rng.normal(size=(40, 5))
    kernel = kernel_points(15, 0.3, 0).astype(np.float64)
    w = rng.normal(size=(15, 5, 4))
    ref = naive_kpconv(q, s, nb, x, kernel, w, 0.2, normalize)
    got = kpconv(torch.from_numpy(q), torch.from_numpy(s), torch.from_numpy(nb), torch.from_numpy(x),
                 torch.from_numpy(kernel), torch.from_numpy(w), 0.2, normalize)
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-9, atol=1e-10)
    assert np.abs(ref).max() > 0.1  # the case is not trivially zero


def test_kpconv_layer_is_translation_invariant_and_differentiable():
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    pts = torch.from_numpy(rng.uniform(0, 1, (60, 3)).astype(np.float32))
    nb = torch.from_numpy(radius_neighbors(pts.numpy(), pts.numpy(), 0.3, 16))
    layer = KPConv(3, 8, radius=0.25, extent=0.2)
    x = torch.randn(60, 3, requires_grad=True)
    y = layer(pts, pts, nb, x)
    y2 = layer(pts + 5.0, pts + 5.0, nb, x)
    torch.testing.assert_close(y, y2, rtol=1e-4, atol=1e-4)
    y.square().sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert layer.weights.grad is not None and layer.weights.grad.abs().sum() > 0
    assert "kernel" in layer.state_dict()  # the disposition travels with checkpoints


def test_grid_subsample_barycentres():
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.01], [0.26, 0.01, 0.01]])
    out = grid_subsample(pts, 0.1)
    assert out.shape == (2, 3)
    np.testing.assert_allclose(sorted(out[:, 0]), [0.02, 0.26], atol=1e-6)
    np.testing.assert_allclose(out[np.argmin(out[:, 0])], [0.02, 0.02, 0.01], atol=1e-6)


def test_grid_subsample_sums_in_point_order():
    """The per-axis bincount sums are np.add.at's (the previous code): the same barycentres bit for bit."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-2.0, 3.0, size=(20000, 3)) * rng.uniform(0.5, 1.5, size=(20000, 1))
    cell = np.floor(pts / 0.07).astype(np.int64)
    cell -= cell.min(axis=0)
    dims = cell.max(axis=0) + 1
    _, inverse, counts = np.unique((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2],
                                   return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, pts)
    assert np.array_equal(grid_subsample(pts, 0.07), (sums / counts[:, None]).astype(np.float32))


def test_radius_neighbors_against_brute_force():
    rng = np.random.default_rng(3)
    s = rng.uniform(0, 1, (200, 3))
    q = rng.uniform(0, 1, (50, 3))
    r = 0.2
    nb = radius_neighbors(q, s, r, 1000)
    d = np.linalg.norm(q[:, None] - s[None], axis=-1)
    for i in range(len(q)):
        row = nb[i][nb[i] < len(s)]
        assert set(row) == set(np.flatnonzero(d[i] < r))
        assert np.all(np.diff(d[i, row]) >= 0)  # nearest first
    assert nb.shape[1] == (d < r).sum(1).max()
    capped = radius_neighbors(q, s, r, 5)
    assert capped.shape[1] == 5
    np.testing.assert_array_equal(capped, nb[:, :5])  # truncation keeps the nearest
    nn1 = nearest_neighbor(q, s)
    np.testing.assert_array_equal(nn1[:, 0], d.argmin(1))


def test_radius_pairs():
    a = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    b = np.array([[0.05, 0, 0], [2.0, 0, 0], [1.0, 0.02, 0]])
    np.testing.assert_array_equal(radius_pairs(a, b, 0.1), [[0, 0], [1, 2]])


@pytest.fixture(scope="module")
def room():
    return box_room(np.random.default_rng(0), size=(3.0, 2.5, 2.0), density=300.0)[0]


def test_pyramid_levels_and_shadow_convention(room):
    spec = PyramidSpec(0.1, 3, 2.5, (30, 30, 30))
    pyr = build_pyramid(room, spec)
    assert len(pyr.points) == 3 and len(pyr.pools) == 2 and len(pyr.upsamples) == 2
    n = [len(p) for p in pyr.points]
    assert n[0] > n[1] > n[2] > 0
    for l in range(3):
        assert pyr.neighbors[l].max() <= n[l] and pyr.neighbors[l].shape[1] <= 30
        # every point is its own nearest neighbour
        np.testing.assert_array_equal(pyr.neighbors[l][:, 0], np.arange(n[l]))
    for l in range(2):
        assert pyr.pools[l].max() <= n[l] and len(pyr.pools[l]) == n[l + 1]
        assert pyr.upsamples[l].shape == (n[l], 1) and pyr.upsamples[l].max() < n[l + 1]


def test_calibrated_limits_are_the_keep_ratio_quantile(room):
    spec = PyramidSpec(0.1, 2, 2.5)
    lim = calibrate_limits([room], spec, keep_ratio=0.8)
    pts = grid_subsample(room, 0.1)
    from pcrcg.models.kpconv.ops import neighbor_counts

    counts = neighbor_counts(pts, pts, 0.25)
    assert lim[0] == int(np.ceil(np.quantile(counts, 0.8)))
    assert 0.75 <= np.mean(counts <= lim[0]) <= 0.9


def _row_sets(a: np.ndarray, n: int) -> list[frozenset]:
    return [frozenset(r[r < n].tolist()) for r in a]


def test_cached_neighbours_are_rotation_invariant(room):
    """Indices computed once in the fragment frame equal a fresh search on the moved points."""
    spec = PyramidSpec(0.1, 3, 2.5, (40, 40, 40))
    pyr = build_pyramid(room, spec)
    rng = np.random.default_rng(7)
    T = make_transform(random_rotation(rng), rng.uniform(-3, 3, 3))
    moved = pyr.transformed(T)
    for l in range(3):
        p = moved.points[l]
        n = len(p)
        fresh = radius_neighbors(p, p, spec.radius(l), spec.limit(l))
        same = np.mean([a == b for a, b in zip(_row_sets(fresh, n), _row_sets(pyr.neighbors[l], n))])
        assert same > 0.999, (l, same)  # only float ties at the radius may differ
        if l < 2:
            fresh_pool = radius_neighbors(moved.points[l + 1], p, spec.radius(l), spec.limit(l))
            same = np.mean([a == b for a, b in zip(_row_sets(fresh_pool, n), _row_sets(pyr.pools[l], n))])
            assert same > 0.999
            np.testing.assert_array_equal(nearest_neighbor(p, moved.points[l + 1]), pyr.upsamples[l])
    # the moved points really are the rigidly moved cached points
    np.testing.assert_allclose(moved.points[0], room_level0(room, spec) @ T[:3, :3].T + T[:3, 3], atol=1e-5)


def room_level0(room, spec):
    return grid_subsample(room, spec.cell(0)).astype(np.float64)


def test_pyramid_cache_memory_and_disk(tmp_path, room):
    spec = PyramidSpec(0.15, 2, 2.5, (20, 20))
    calls = []

    def build():
        calls.append(1)
        return build_pyramid(room, spec)

    cache = PyramidCache(maxsize=4, directory=tmp_path)
    key = ("root", "scene", 3, spec.key())
    a = cache.get(key, build)
    b = cache.get(key, build)
    assert a is b and len(calls) == 1
    fresh = PyramidCache(maxsize=4, directory=tmp_path)  # a new process: read from disk
    c = fresh.get(key, build)
    assert len(calls) == 1 and fresh.hits == 1
    for name in ("points", "neighbors", "pools", "upsamples"):
        for x, y in zip(getattr(a, name), getattr(c, name)):
            np.testing.assert_array_equal(x, y)


def test_pyramid_cache_file_of_other_points_is_built_again(tmp_path, room):
    """A data set made again at the same root: same key, other points. The file made from the old points
    is not used; it is overwritten, and the new points' file is then read."""
    from pcrcg.models.kpconv.pyramid import points_fingerprint

    spec = PyramidSpec(0.15, 2, 2.5, (20, 20))
    key = ("root", "scene", 3, spec.key())
    moved = room + np.array([0.05, 0.0, 0.0], dtype=room.dtype)
    calls = []

    def get(cache, pts):
        return cache.get(key, lambda: (calls.append(1), build_pyramid(pts, spec))[1], lambda: points_fingerprint(pts))

    get(PyramidCache(maxsize=4, directory=tmp_path), room)
    fresh = get(PyramidCache(maxsize=4, directory=tmp_path), moved)  # a new process, regenerated data
    assert len(calls) == 2
    np.testing.assert_array_equal(fresh.points[0], build_pyramid(moved, spec).points[0])
    again = PyramidCache(maxsize=4, directory=tmp_path)
    get(again, moved)
    assert len(calls) == 2 and again.hits == 1
    assert points_fingerprint(room) != points_fingerprint(moved)
    # the training collate passes the points' fingerprint: a data set made again at the same root is rebuilt
    from pcrcg.models.datamodule import PairCollate

    for pts in (room, moved):
        col = PairCollate(spec, 0.1, cache=PyramidCache(0, tmp_path / "collate"), root="root")
        np.testing.assert_array_equal(col.pyramid("scene", 3, pts).points[0], build_pyramid(pts, spec).points[0])
    other = np.float32 if room.dtype == np.float64 else np.float64
    assert points_fingerprint(room) != points_fingerprint(room.astype(other))  # the same numbers, other bytes


def test_a_pyramid_cache_that_cannot_be_written_warns_once_and_builds(tmp_path, room, monkeypatch):
    spec = PyramidSpec(0.15, 2, 2.5, (20, 20))
    cache = PyramidCache(maxsize=0, directory=tmp_path)

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    with pytest.warns(UserWarning, match="not written") as caught:
        for frag in range(3):
            cache.get(("root", "scene", frag, spec.key()), lambda: build_pyramid(room, spec))
    assert len(caught) == 1 and cache.misses == 3 and not list(tmp_path.iterdir())


def test_stack_pair_offsets_and_shadows():
    rng = np.random.default_rng(5)
    spec = PyramidSpec(0.1, 2, 2.5, (16, 16))
    a = build_pyramid(rng.uniform(0, 1, (400, 3)), spec)
    b = build_pyramid(rng.uniform(0, 1, (300, 3)) + 5, spec)
    st = stack_pair(a, b)
    for l in range(2):
        na, nb_ = len(a.points[l]), len(b.points[l])
        nbr = st.neighbors[l].numpy()
        assert st.lengths[l].tolist() == [na, nb_]
        assert nbr.max() == na + nb_  # shadow = total count
        src_rows, tgt_rows = nbr[:na], nbr[na:]
        real = src_rows[src_rows < na + nb_]
        assert real.max() < na  # source rows only reach source points
        real_t = tgt_rows[tgt_rows < na + nb_]
        assert real_t.min() >= na
        np.testing.assert_array_equal(tgt_rows[:, 0], np.arange(na, na + nb_))
    up = st.upsamples[0].numpy()
    n1a = len(a.points[1])
    assert up[: len(a.points[0])].max() < n1a and up[len(a.points[0]):].min() >= n1a


def test_influence_cache_is_shared_within_a_level_and_exact():
    rng = np.random.default_rng(4)
    pts = torch.from_numpy(rng.uniform(0, 1, (80, 3)).astype(np.float32))
    nb = torch.from_numpy(radius_neighbors(pts.numpy(), pts.numpy(), 0.3, 16))
    a, b = KPConv(4, 6, radius=0.25, extent=0.2), KPConv(6, 6, radius=0.25, extent=0.2)
    c = KPConv(4, 6, radius=0.5, extent=0.4)  # another level: its own influence
    x = torch.randn(80, 4)
    cache: dict = {}
    ya = a(pts, pts, nb, x, cache)
    assert len(cache) == 1
    yb = b(pts, pts, nb, torch.randn(80, 6), cache)
    assert len(cache) == 1  # same neighbours, kernel and extent: shared
    c(pts, pts, nb, x, cache)
    assert len(cache) == 2
    torch.testing.assert_close(ya, a(pts, pts, nb, x))  # identical to the uncached path
    assert yb.shape == (80, 6)


def test_a_fragments_pyramid_does_not_depend_on_where_its_data_set_lies():
    """The draw that caps level 0 is seeded by the fragment, not by the data root's path: the same data in
    another folder (a copy, another checkout) gives the same pyramids; another fragment gets another draw."""
    from pcrcg.models.datamodule import PairCollate
    from pcrcg.models.kpconv import PyramidSpec
    from pcrcg.testing.pairs import toy_pair

    s = toy_pair(0, density=80.0)
    spec = PyramidSpec(0.1, 3, 2.5, (), max_points=len(s.src_points) // 2)  # a cap: a random half is kept
    here = PairCollate(spec, 0.15, root="/data/synthmatch-cpu").pyramid("scene-a", 3, s.src_points)
    there = PairCollate(spec, 0.15, root="/elsewhere/copy/synthmatch-cpu").pyramid("scene-a", 3, s.src_points)
    other = PairCollate(spec, 0.15, root="/data/synthmatch-cpu").pyramid("scene-a", 4, s.src_points)
    assert len(here.points[0]) == spec.max_points
    for a, b in zip(here.points + here.neighbors, there.points + there.neighbors):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(here.points[0], other.points[0])
