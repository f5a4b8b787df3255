"""Tests that only mean something on a GPU: the CUDA paths the CPU never takes. Marked ``gpu``, they are
skipped where torch sees no CUDA device (tests/conftest.py); ``pytest -m gpu`` runs only them.

On a GPU, KPConv's ``auto`` implementation takes the dense path (the sparse aggregation is CPU-only), and
every ``auto`` device resolves to CUDA: these tests hold both to the CPU's results and choices."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pcrcg.models.kpconv import KPConv, kernel_points, kpconv, radius_neighbors
from test_kpconv import naive_kpconv

pytestmark = pytest.mark.gpu


def test_kpconv_on_the_gpu_matches_the_naive_loop():
    rng = np.random.default_rng(1)
    s = rng.uniform(0, 1, (40, 3))
    q = s[::3] + rng.normal(0, 0.01, (len(s[::3]), 3))
    nb = radius_neighbors(q, s, 0.35, 12)
    x = rng.normal(size=(40, 5))
    kernel = kernel_points(15, 0.3, 0).astype(np.float64)
    w = rng.normal(size=(15, 5, 4))
    ref = naive_kpconv(q, s, nb, x, kernel, w, 0.2)
    got = kpconv(*(torch.from_numpy(a).cuda() for a in (q, s, nb, x, kernel, w)), 0.2)
    assert got.device.type == "cuda"
    np.testing.assert_allclose(got.cpu().numpy(), ref, rtol=1e-9, atol=1e-10)
    assert np.abs(ref).max() > 0.1  # the case is not trivially zero


def test_kpconv_layer_on_the_gpu_matches_the_cpu():
    """The same layer and inputs: CPU (sparse aggregation) and GPU (dense) agree, forward and backward."""
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    pts = torch.from_numpy(rng.uniform(0, 1, (300, 3)).astype(np.float32))
    nb = torch.from_numpy(radius_neighbors(pts.numpy(), pts.numpy(), 0.2, 24))
    layer = KPConv(6, 8, radius=0.15, extent=0.12)
    x = torch.randn(300, 6)
    outputs, grads = [], []
    for device in ("cpu", "cuda"):
        layer_d = layer.to(device)
        layer_d.zero_grad()
        y = layer_d(pts.to(device), pts.to(device), nb.to(device), x.to(device))
        y.square().sum().backward()
        outputs.append(y.detach().cpu())
        grads.append(layer_d.weights.grad.detach().cpu())
    assert outputs[0].abs().max() > 0.1
    torch.testing.assert_close(outputs[1], outputs[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-3, atol=1e-4)


def test_every_auto_device_is_the_gpu():
    import pcrcg.evaluation.stage
    import pcrcg.models.train
    import pcrcg.pipeline
    import pcrcg.pretrain2d.core
    import pcrcg.vision.learned
    from pcrcg.device import resolve_device

    # every stage resolves "auto" with the one resolver (strings; callers wanting a torch.device wrap it)
    assert resolve_device("auto") == "cuda" and resolve_device(None) == "cuda" and resolve_device("cpu") == "cpu"
    assert torch.device(resolve_device("auto")).type == "cuda"
    for stage in (pcrcg.pipeline, pcrcg.pretrain2d.core, pcrcg.vision.learned, pcrcg.models.train, pcrcg.evaluation.stage):
        assert stage.resolve_device is resolve_device, stage.__name__
