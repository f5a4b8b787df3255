"""The fast paths of the training step against the implementations they replace, on fixed inputs:
the sparse KPConv aggregation (``pcrcg.models.kpconv.aggregation``) against the dense reference
(``kpconv``), layer by layer and through a whole Predator forward + backward; outputs and gradients
must agree to float rounding (float64: to ~1e-12, i.e. the same sums in another order)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.models.datamodule import PairCollate
from pcrcg.models.kpconv import (
    KernelAggregation,
    KPConv,
    PyramidSpec,
    calibrate_limits,
    get_implementation,
    implementation,
    kernel_points,
    kpconv,
    kpconv_sparse,
    radius_neighbors,
)
from pcrcg.models.kpconv.blocks import PointNorm, max_over_neighbours, max_pool, max_pool_reference, normalize_channels
from pcrcg.models.kpconv.conv import kernel_influence
from pcrcg.models.predator import build_predator
from pcrcg.testing.pairs import toy_pair


def _geometry(seed: int, n: int = 300, strided: bool = False, dtype=np.float32):
    """Supports, queries (every 3rd support when strided) and radius neighbours with shadow padding."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0, 1, (n, 3))
    q = s[::3] + rng.normal(0, 0.01, (len(s[::3]), 3)) if strided else s
    nb = radius_neighbors(q, s, 0.2, 24)
    assert (nb == n).any() and (nb < n).any()  # shadows and real neighbours are both exercised
    return torch.from_numpy(q.astype(dtype)), torch.from_numpy(s.astype(dtype)), torch.from_numpy(nb)


def _both(q, s, nb, kernel, extent, feats, weights, normalize=True):
    """(output, grad feats, grad weights) of the dense reference and of the sparse path."""
    res = []
    g = torch.randn(q.shape[0], weights.shape[2], dtype=feats.dtype, generator=torch.Generator().manual_seed(9))
    for sparse in (False, True):
        f, w = feats.clone().requires_grad_(True), weights.clone().requires_grad_(True)
        if sparse:
            out = kpconv_sparse(f, KernelAggregation(q, s, nb, kernel, extent), w, normalize)
        else:
            out = kpconv(q, s, nb, f, kernel, w, extent, normalize)
        (out * g).sum().backward()
        res.append((out.detach(), f.grad, w.grad))
    return res


@pytest.mark.parametrize("strided", [False, True])
@pytest.mark.parametrize("normalize", [True, False])
def test_sparse_kpconv_equals_dense_reference_float64(strided, normalize):
    q, s, nb = _geometry(1, strided=strided, dtype=np.float64)
    kernel = torch.from_numpy(kernel_points(15, 0.15, 0).astype(np.float64))
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(s.shape[0], 5, dtype=torch.float64, generator=gen)
    weights = torch.randn(15, 5, 7, dtype=torch.float64, generator=gen)
    (o1, f1, w1), (o2, f2, w2) = _both(q, s, nb, kernel, 0.12, feats, weights, normalize)
    assert o1.abs().max() > 0.1 and f1.abs().max() > 0.1  # not trivially zero
    for a, b in ((o1, o2), (f1, f2), (w1, w2)):
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("strided", [False, True])
def test_sparse_kpconv_equals_dense_reference_float32(strided):
    q, s, nb = _geometry(2, strided=strided)
    kernel = torch.from_numpy(kernel_points(15, 0.15, 0))
    gen = torch.Generator().manual_seed(1)
    feats, weights = torch.randn(s.shape[0], 8, generator=gen), torch.randn(15, 8, 8, generator=gen)
    (o1, f1, w1), (o2, f2, w2) = _both(q, s, nb, kernel, 0.12, feats, weights)
    for a, b in ((o1, o2), (f1, f2), (w1, w2)):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-5 * float(a.abs().max()))


def test_sparse_influences_are_the_reference_bit_for_bit_and_the_matrices_valid():
    q, s, nb = _geometry(3, strided=True)
    kernel = torch.from_numpy(kernel_points(15, 0.15, 0))
    agg = KernelAggregation(q, s, nb, kernel, 0.12)
    ref = kernel_influence(q, s, nb, kernel, 0.12)  # (M, H, K)
    m, h = nb.shape
    dense = torch.full((m, s.shape[0] + 1, 15), float("nan"))
    dense[torch.arange(m).unsqueeze(1).expand(m, h), nb] = ref
    got = dense[agg._rows.long(), agg._cols.long()]  # (E, K) of the real (query, support) pairs
    assert torch.equal(got.t(), agg._infl_t)
    assert agg._rows.numel() == int((nb < s.shape[0]).sum())  # exactly the real neighbours
    torch.testing.assert_close(agg.count, (nb < s.shape[0]).sum(1))
    for mat in (agg.forward_matrix(torch.float32), agg.backward_matrix(torch.float32)):
        # sorted, distinct columns per row, in range: torch's CSR invariants (raises otherwise)
        torch.sparse_csr_tensor(mat.crow_indices(), mat.col_indices(), mat.values(), mat.shape,
                                check_invariants=True)
    # the transpose is the transpose, bit for bit (its values are gathered, not computed again)
    m_, k_, n_ = agg.shape
    fwd = agg.forward_matrix(torch.float32).to_dense().view(k_, m_, n_).transpose(0, 1).reshape(m_ * k_, n_)
    assert torch.equal(agg.backward_matrix(torch.float32).to_dense(), fwd.t())


def test_sparse_aggregation_cpu_shortcuts_give_the_integers_and_values_of_the_plain_formulas():
    """The CPU build's NumPy pair list, radix order and buffered copies against the formulas they replace
    (torch's sort / nonzero / division, stable argsort, ``repeat`` and ``.t().reshape``): equal bit for bit."""
    from pcrcg.models.kpconv.aggregation import _real_pairs_cpu, _support_order

    q, s, nb = _geometry(6, strided=True)
    n = s.shape[0]
    rows, cols, count = _real_pairs_cpu(nb, n, torch.int32)
    sorted_nb = torch.sort(nb, dim=1).values
    valid = sorted_nb < n
    flat = valid.reshape(-1).nonzero().squeeze(1)
    assert torch.equal(rows, torch.div(flat, nb.shape[1], rounding_mode="floor").to(torch.int32))
    assert torch.equal(cols, sorted_nb.reshape(-1).index_select(0, flat).to(torch.int32))
    assert torch.equal(count, valid.sum(dim=1)) and count.dtype == torch.int64
    # the stable order by support, on the radix path (n <= 65,536) and on torch's, with many ties
    rng = np.random.default_rng(0)
    for high in (50, 70_000):
        c = torch.from_numpy(rng.integers(0, high, 5000).astype(np.int32))
        assert torch.equal(_support_order(c, high), torch.argsort(c, stable=True))
    kernel = torch.from_numpy(kernel_points(15, 0.15, 0))
    agg = KernelAggregation(q, s, nb, kernel, 0.12)
    m, k, _ = agg.shape
    infl, order = agg._infl_t, torch.argsort(cols, stable=True)
    fwd, bwd = agg.forward_matrix(torch.float32), agg.backward_matrix(torch.float32)
    assert torch.equal(fwd.col_indices(), cols.repeat(k)) and torch.equal(fwd.values(), infl.reshape(-1))
    assert torch.equal(bwd.values(), infl.index_select(1, order).t().reshape(-1))
    assert torch.equal(bwd.col_indices(),
                       ((rows.index_select(0, order) * k).unsqueeze(1) + torch.arange(k, dtype=torch.int32)).reshape(-1))
    # the forward's kernel-major rows turned query-major, one channel (a view) and several (a copy)
    for c in (1, 5):
        f = torch.randn(n, c, generator=torch.Generator().manual_seed(c))
        assert torch.equal(agg(f), (fwd @ f).view(k, m, c).transpose(0, 1).reshape(m, k * c))


def test_sparse_kpconv_queries_without_neighbours_and_empty_inputs():
    q, s, nb = _geometry(4)
    nb = nb.clone()
    nb[:5] = s.shape[0]  # five queries see only shadows
    kernel = torch.from_numpy(kernel_points(15, 0.15, 0))
    gen = torch.Generator().manual_seed(2)
    feats, weights = torch.randn(s.shape[0], 4, generator=gen), torch.randn(15, 4, 3, generator=gen)
    (o1, f1, w1), (o2, f2, w2) = _both(q, s, nb, kernel, 0.12, feats, weights)
    assert torch.equal(o2[:5], torch.zeros(5, 3))
    for a, b in ((o1, o2), (f1, f2), (w1, w2)):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-5)
    empty = torch.zeros((0, nb.shape[1]), dtype=torch.long)
    out = kpconv_sparse(feats, KernelAggregation(q[:0], s, empty, kernel, 0.12), weights)
    assert out.shape == (0, 3)
    all_shadow = torch.full((3, 4), s.shape[0], dtype=torch.long)
    f = feats.clone().requires_grad_(True)
    out = kpconv_sparse(f, KernelAggregation(q[:3], s, all_shadow, kernel, 0.12), weights)
    out.sum().backward()
    assert torch.equal(out, torch.zeros(3, 3)) and torch.equal(f.grad, torch.zeros_like(feats))


def test_layer_implementation_switch_and_auto_choice():
    q, s, nb = _geometry(5)
    torch.manual_seed(0)
    layer = KPConv(4, 6, radius=0.15, extent=0.12)
    x = torch.randn(s.shape[0], 4)
    assert get_implementation() == "auto"
    outs, keys = {}, {}
    for name in ("dense", "sparse", "auto"):
        cache: dict = {}
        with implementation(name):
            outs[name] = layer(q, s, nb, x, cache)
        keys[name] = {k[0] for k in cache}
    assert get_implementation() == "auto"  # restored
    assert keys == {"dense": {"dense"}, "sparse": {"sparse"}, "auto": {"sparse"}}  # auto: sparse on the CPU
    torch.testing.assert_close(outs["sparse"], outs["dense"], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError):
        with implementation("fused"):
            pass


def test_max_pool_equals_reference_with_gradients():
    rng = np.random.default_rng(6)
    x = torch.from_numpy(rng.normal(size=(50, 6)).astype(np.float32))
    x[7] = x[3]  # ties: the first maximum gets the gradient, in both
    inds = torch.from_numpy(rng.integers(0, 51, (30, 8)))  # 50 = shadow (zero feature)
    inds[0] = 50
    g = torch.from_numpy(rng.normal(size=(30, 6)).astype(np.float32))
    res = []
    for fn in (max_pool_reference, max_pool):
        xx = x.clone().requires_grad_(True)
        out = fn(xx, inds)
        (out * g).sum().backward()
        res.append((out.detach(), xx.grad))
    assert torch.equal(res[0][0], res[1][0])
    torch.testing.assert_close(res[1][1], res[0][1], rtol=1e-6, atol=1e-6)
    assert res[0][1].abs().sum() > 0


def test_max_over_neighbours_is_max_values_bit_for_bit_with_ties():
    gen = torch.Generator().manual_seed(7)
    x = torch.randn(40, 6, 5, generator=gen)
    x[3, 4] = x[3, 1]  # a tie: the first maximum gets the gradient
    x[5, :, 2] = 0.0  # a whole column tied
    x[3, 1] = x[3].max(0).values + 1.0
    x[3, 4] = x[3, 1]
    g = torch.randn(40, 5, generator=gen)
    res = []
    for fn in (lambda t: t.max(dim=1).values, max_over_neighbours):
        xx = x.clone().requires_grad_(True)
        out = fn(xx)
        (out * g).sum().backward()
        res.append((out.detach(), xx.grad))
    assert torch.equal(res[0][0], res[1][0]) and torch.equal(res[0][1], res[1][1])
    assert res[1][1][3, 1].abs().sum() > 0 and res[1][1][3, 4].abs().sum() == 0
    with torch.no_grad():
        assert torch.equal(max_over_neighbours(x), x.max(dim=1).values)
    inds = torch.randint(0, 41, (30, 7), generator=gen)
    with torch.no_grad():  # max_pool's inference path
        assert torch.equal(max_pool(x[:, 0], inds), max_pool_reference(x[:, 0], inds))


@pytest.mark.parametrize("dims", [(0,), (0, 1)])
def test_channel_normalisation_equals_var_mean_reference(dims):
    gen = torch.Generator().manual_seed(3)
    x = (torch.randn(400, 10, 6, dtype=torch.float64, generator=gen) * 5 + 3)[:, :, :] if dims == (0, 1) else (
        torch.randn(700, 6, dtype=torch.float64, generator=gen) * 5 + 3)
    g = torch.randn(x.shape, dtype=torch.float64, generator=gen)
    res = {}
    for name in ("dense", "auto"):
        xx = x.clone().requires_grad_(True)
        with implementation(name):
            y = normalize_channels(xx, dims, 1e-5)
        (y * g).sum().backward()
        res[name] = (y.detach(), xx.grad)
    for a, b in zip(res["dense"], res["auto"]):
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12)
    # and what it is: zero mean, unit variance per channel
    y = res["auto"][0]
    torch.testing.assert_close(y.mean(dims), torch.zeros(6, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close(y.var(dims, unbiased=False), torch.ones(6, dtype=torch.float64), rtol=1e-6, atol=0)
    x32 = x.float()
    with implementation("dense"):
        ref = PointNorm(6)(x32.reshape(-1, 6))
    torch.testing.assert_close(PointNorm(6)(x32.reshape(-1, 6)), ref, rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def toy_batch():
    s = toy_pair(1, size=(2.0, 1.6, 1.5), density=100.0)
    spec = PyramidSpec(0.12, 3, 2.5)
    spec = PyramidSpec(0.12, 3, 2.5, calibrate_limits([s.src_points, s.tgt_points], spec))
    return PairCollate(spec, overlap_radius=0.18)([s])


def test_predator_forward_and_backward_equal_with_dense_and_sparse_kpconv(toy_batch):
    """The whole network (encoder, strided blocks, attention, decoder) on a toy pair, twice, in
    float64 (its normalisations amplify float32 rounding to ~1e-4 of the largest gradients)."""
    cfg = dict(voxel_size=0.12, num_layers=3, first_dim=16, final_dim=8, gnn_dim=16, num_heads=2, dgcnn_k=4)
    torch.manual_seed(0)
    net = build_predator(cfg, in_dim=1).double()
    pyr = toy_batch.pyramid
    pyr64 = type(pyr)([p.double() for p in pyr.points], pyr.neighbors, pyr.pools, pyr.upsamples, pyr.lengths)
    n0 = pyr.points[0].shape[0]
    feats = torch.ones(n0, 1, dtype=torch.float64)
    res = {}
    for name in ("dense", "sparse"):
        pyr64.cache.clear()
        net.zero_grad()
        with implementation(name):
            out = net(feats, pyr64)
            weights = torch.linspace(-1, 1, n0, dtype=torch.float64)
            loss = (out.descriptors[:, 0] * weights).sum() + out.overlap_logits.square().mean()
            loss.backward()
        res[name] = (out, {k: p.grad.clone() for k, p in net.named_parameters() if p.grad is not None})
    (od, gd), (os_, gs) = res["dense"], res["sparse"]
    for a, b in ((od.descriptors, os_.descriptors), (od.overlap_logits, os_.overlap_logits),
                 (od.matchability_logits, os_.matchability_logits)):
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-10)
    assert gd.keys() == gs.keys() and any("encoder.0.conv" in k for k in gd)
    for k in gd:
        torch.testing.assert_close(gs[k], gd[k], rtol=1e-8, atol=1e-9 * max(1.0, float(gd[k].abs().max())))


# --------------------------------------------------------------------------- circle loss


def _circle_inputs(seed: int, n: int, m: int, dtype=torch.float64):
    """Coordinates whose radius masks give a few positives per row (some rows none, one row all) and
    descriptor distances in [0, 2]."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(n, 3, generator=gen, dtype=dtype)
    b = torch.cat([a[: min(n, m)] + 0.01 * torch.randn(min(n, m), 3, generator=gen, dtype=dtype),
                   torch.rand(max(0, m - n), 3, generator=gen, dtype=dtype)])
    coords = torch.cdist(a, b)
    coords[0] = 0.01  # a row of positives only (its positive logits have no zeros)
    desc_a = torch.nn.functional.normalize(torch.randn(n, 8, generator=gen, dtype=dtype), dim=1)
    desc_b = torch.nn.functional.normalize(torch.randn(m, 8, generator=gen, dtype=dtype), dim=1)
    desc_b[: min(n, m)] = torch.nn.functional.normalize(desc_b[: min(n, m)] + 2 * desc_a[: min(n, m)], dim=1)
    fd = torch.sqrt(torch.clamp(2.0 - 2.0 * desc_a @ desc_b.t(), min=1e-12))
    return coords, fd


@pytest.mark.parametrize("scaled", [False, True])
@pytest.mark.parametrize("shape", [(60, 45), (45, 60), (3, 40)])
def test_circle_loss_equals_reference_float64(shape, scaled):
    from pcrcg.models.losses import masked_circle_loss, masked_circle_loss_reference

    coords, fd = _circle_inputs(0, *shape)
    pos, neg = coords < 0.08, coords > 0.2
    assert pos.any() and neg.any()
    scales = torch.rand(shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64) if scaled else None
    res = []
    for fn in (masked_circle_loss_reference, masked_circle_loss):
        f = fd.clone().requires_grad_(True)
        loss = fn(pos, neg, f, 0.1, 1.4, 0.1, 1.4, 16.0, scales)
        loss.backward()
        res.append((loss.detach(), f.grad))
    (l1, g1), (l2, g2) = res
    assert float(l1) > 0.1 and g1.abs().max() > 1e-4
    torch.testing.assert_close(l2, l1, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g2, g1, rtol=1e-10, atol=1e-12)
    with implementation("dense"):  # the previous code, reachable for the benchmark
        torch.testing.assert_close(masked_circle_loss(pos, neg, fd, pos_scales=scales),
                                   masked_circle_loss_reference(pos, neg, fd, pos_scales=scales), rtol=0, atol=0)


def test_circle_loss_float32_and_degenerate_masks():
    from pcrcg.models.losses import masked_circle_loss, masked_circle_loss_reference

    coords, fd = _circle_inputs(1, 200, 180, torch.float32)
    for pos, neg in ((coords < 0.06, coords > 0.15),  # the usual case
                     (coords < 0.06, torch.zeros_like(coords, dtype=torch.bool)),  # no negatives: 0
                     (torch.zeros_like(coords, dtype=torch.bool), coords > 0.15),  # no positives: 0
                     (coords < 0.06, coords > 10.0)):
        res = []
        for fn in (masked_circle_loss_reference, masked_circle_loss):
            f = fd.clone().requires_grad_(True)
            loss = fn(pos, neg, f)
            loss.backward()
            res.append((loss.detach(), f.grad))
        (l1, g1), (l2, g2) = res
        torch.testing.assert_close(l2, l1, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(g2, g1, rtol=1e-5, atol=1e-6 * max(1.0, float(g1.abs().max())))


def test_predator_loss_stats_equal_with_the_previous_code(toy_batch):
    """PredatorLoss (circle loss with its shared positives mask, hit rate, overlap, matchability) gives
    the reference's statistics and descriptor gradients."""
    from pcrcg.models.losses import LossConfig, PredatorLoss

    crit = PredatorLoss(LossConfig(max_points=64), 0.12)
    pts = toy_batch.pyramid.points[0].double()
    gen = torch.Generator().manual_seed(0)
    desc0 = torch.nn.functional.normalize(torch.randn(len(pts), 8, generator=gen, dtype=torch.float64), dim=1)
    logits = torch.randn(len(pts), generator=gen, dtype=torch.float64)
    res = []
    for name in ("dense", "auto"):
        desc = desc0.clone().requires_grad_(True)
        with implementation(name):
            stats = crit(desc, logits, logits, pts, toy_batch.n_src, toy_batch.transform.double(), toy_batch.corr,
                         generator=torch.Generator().manual_seed(5))
        stats["loss"].backward()
        res.append(({k: v.detach() for k, v in stats.items()}, desc.grad))
    (s1, g1), (s2, g2) = res
    assert s1.keys() == s2.keys() and float(s1["circle_loss"]) > 0
    for k in s1:
        torch.testing.assert_close(s2[k], s1[k], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g2, g1, rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------- overlap attention


def test_edge_linear_equals_linear_of_edge_features():
    from pcrcg.models.predator import edge_features, edge_linear, knn_indices

    gen = torch.Generator().manual_seed(0)
    coords = torch.rand(70, 3, generator=gen, dtype=torch.float64)
    x = torch.randn(70, 6, generator=gen, dtype=torch.float64)
    idx = knn_indices(coords, 5)
    lin = torch.nn.Linear(12, 9, bias=False).double()
    res = []
    for fast in (False, True):
        xx = x.clone().requires_grad_(True)
        lin.zero_grad()
        y = edge_linear(lin, xx, idx) if fast else lin(edge_features(xx, idx))
        (y * torch.linspace(-1, 1, y.numel(), dtype=torch.float64).view_as(y)).sum().backward()
        res.append((y.detach(), xx.grad, lin.weight.grad.clone()))
    for a, b in zip(*res):
        torch.testing.assert_close(b, a, rtol=1e-12, atol=1e-12)


def test_overlap_attention_equals_previous_code_float64():
    """The bottleneck's attention (self layers with the shared k-NN graphs and per-point edge products,
    cross layers) against the previous code, outputs and gradients of inputs and parameters."""
    from pcrcg.models.predator import OverlapAttention

    torch.manual_seed(0)
    att = OverlapAttention(16, 2, 6, ("self", "cross", "self")).double()
    gen = torch.Generator().manual_seed(1)
    xyz = torch.rand(90, 3, generator=gen, dtype=torch.float64)
    x0 = torch.randn(90, 16, generator=gen, dtype=torch.float64)
    res = []
    for name in ("dense", "auto"):
        att.zero_grad()
        x = x0.clone().requires_grad_(True)
        with implementation(name):
            s, t = att(xyz[:50], xyz[50:], x[:50], x[50:])
            (s.square().sum() + (t * torch.linspace(-1, 1, t.numel(), dtype=torch.float64).view_as(t)).sum()).backward()
        res.append((torch.cat([s, t]).detach(), x.grad, {k: p.grad.clone() for k, p in att.named_parameters()}))
    (o1, g1, p1), (o2, g2, p2) = res
    torch.testing.assert_close(o2, o1, rtol=1e-10, atol=1e-11)
    torch.testing.assert_close(g2, g1, rtol=1e-9, atol=1e-10 * float(g1.abs().max()))
    for k in p1:
        torch.testing.assert_close(p2[k], p1[k], rtol=1e-9, atol=1e-10 * max(1.0, float(p1[k].abs().max())))


@pytest.mark.parametrize("dims", [(0,), (0, 1)])
def test_channel_normalisation_closed_form_backward_equals_autograd_of_the_formula(dims):
    """The default normalisation's values are the two-pass formula bit for bit (float32), with and without
    gradients; its closed-form backward equals autograd's through the formula to float rounding."""
    gen = torch.Generator().manual_seed(4)
    shape = (300, 7, 5) if dims == (0, 1) else (500, 5)

    def formula(x):
        n = x.shape[0] * (x.shape[1] if dims == (0, 1) else 1)
        dev = x - x.sum(dim=dims, keepdim=True) / n
        var = (dev * dev).sum(dim=dims, keepdim=True) / n
        return dev * torch.rsqrt(var + 1e-5)

    for dtype in (torch.float32, torch.float64):
        x = torch.randn(shape, dtype=dtype, generator=gen) * 3 - 1
        g = torch.randn(shape, dtype=dtype, generator=gen)
        res = []
        for fn in (formula, lambda t: normalize_channels(t, dims, 1e-5)):
            xx = x.clone().requires_grad_(True)
            y = fn(xx)
            (y * g).sum().backward()
            res.append((y.detach(), xx.grad))
        (y1, g1), (y2, g2) = res
        assert torch.equal(y2, y1)
        with torch.no_grad():
            assert torch.equal(normalize_channels(x, dims, 1e-5), y1)
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(g2, g1, rtol=tol, atol=tol)


def test_matchability_labels_by_blocks_equal_the_full_score_matrix():
    """The labels' arg-maxes over blocks of rows (and of the transposed products) are those of the full
    (n, m) score matrix, on sizes spanning several blocks, with duplicated descriptors (ties: the first
    maximum, as argmax)."""
    from pcrcg.models.losses import _best_scores, matchability_labels

    gen = torch.Generator().manual_seed(7)
    a = torch.nn.functional.normalize(torch.randn(1300, 32, generator=gen), dim=1)
    b = torch.nn.functional.normalize(torch.randn(1100, 32, generator=gen), dim=1)
    b[700] = b[20]  # a tie in every row whose best is b[20]
    a[1000] = a[3]
    full = a @ b.t()
    assert torch.equal(_best_scores(a, b), full.argmax(1)) and torch.equal(_best_scores(b, a), full.argmax(0))
    xa, xb = torch.rand(1300, 3, generator=gen), torch.rand(1100, 3, generator=gen)
    with implementation("dense"):
        ref = matchability_labels(xa, xb, a, b, 0.3)
    got = matchability_labels(xa, xb, a, b, 0.3)
    assert 0 < float(ref[0].mean()) < 1
    assert all(torch.equal(x, y) for x, y in zip(got, ref))


def test_row_arg_max_and_min_by_numpy_give_torchs_indices():
    """pcrcg.device.argmax_rows / argmin_rows: torch's indices for float32 and float64 rows with ties (the first),
    NaN (the first NaN counts as the extreme) and infinities, strided views, a tensor that needs a gradient and an
    empty batch; other dtypes and shapes are torch's own."""
    from pcrcg.device import argmax_rows, argmin_rows

    nan, inf = float("nan"), float("inf")
    small = torch.tensor([[1., 3., 3., 0.], [nan, 1., nan, 2.], [0., 0., 0., 0.], [2., inf, inf, -inf], [-inf, 5., -inf, 5.]])
    gen = torch.Generator().manual_seed(3)
    big = torch.randn(300, 700, generator=gen)
    big[:, 10] = big[:, 600]  # ties across the row
    cases = [small, small.double(), big, big.t()[::3], big[:, ::2], big.clone().requires_grad_(True),
             torch.zeros(0, 5), torch.randint(0, 4, (50, 9))]
    for x in cases:
        for mine, ref in ((argmax_rows(x), x.argmax(1)), (argmin_rows(x), x.argmin(1))):
            assert mine.dtype == torch.int64 and torch.equal(mine, ref)
    assert argmax_rows(small).tolist() == [1, 0, 0, 1, 1] and argmin_rows(small).tolist() == [3, 0, 0, 3, 0]
    one = torch.tensor([3., 1., 2.])  # 1-D: torch's
    assert int(argmax_rows(one.unsqueeze(0))) == 0 and int(argmin_rows(one.unsqueeze(0))) == 1
