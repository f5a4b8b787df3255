"""Rigid KPConv kernel dispositions, computed by the project (no files downloaded or shipped).

A disposition is ``K`` points in the unit ball with one point fixed at the centre. The other
``K - 1`` points minimise an electrostatic-like energy

    E(x) = sum_{a<b} 1 / |x_a - x_b|  +  w * sum_a |x_a|^2

(mutual repulsion, the centre included, plus a quadratic pull towards the centre), from several
seeded random starts; the lowest-energy result is kept and rescaled so that the mean distance of the
non-centre points to the centre is ``ratio`` (0.66, KPConv's choice). The result is a deterministic
function of ``(K, seed)``; models also store their kernel points in their state dict, so a
checkpoint never depends on this computation being bit-identical across library versions.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.optimize import minimize


def _energy_and_grad(flat: np.ndarray, n_free: int, pull: float) -> tuple[float, np.ndarray]:
    """Energy and gradient of the free points (``flat`` is (n_free*3,)); the centre sits at 0."""
    free = flat.reshape(n_free, 3)
    pts = np.vstack([np.zeros((1, 3)), free])  # (K, 3)
    diff = pts[:, None, :] - pts[None, :, :]  # (K, K, 3)
    d2 = np.sum(diff**2, axis=-1)
    np.fill_diagonal(d2, 1.0)
    inv = 1.0 / np.sqrt(d2)
    np.fill_diagonal(inv, 0.0)
    energy = 0.5 * float(np.sum(inv)) + pull * float(np.sum(free**2))
    # d/dx_a sum_b 1/|x_a - x_b| = -sum_b (x_a - x_b) / |x_a - x_b|^3
    grad_all = -np.sum(diff * (inv**3)[:, :, None], axis=1)
    grad = grad_all[1:] + 2.0 * pull * free
    return energy, grad.ravel()


def optimise_disposition(
    n_points: int = 15, seed: int = 0, n_starts: int = 8, pull: float = 5.0, ratio: float = 0.66
) -> np.ndarray:
    """Kernel points (n_points, 3) float64: point 0 is the centre, mean radius of the others = ``ratio``."""
    if n_points < 2:
        raise ValueError(f"a kernel needs at least 2 points, got {n_points}")
    rng = np.random.default_rng(seed)
    n_free = n_points - 1
    best, best_e = None, np.inf
    for _ in range(n_starts):
        x0 = rng.normal(size=(n_free, 3))
        x0 *= (0.5 + 0.5 * rng.random((n_free, 1))) / np.linalg.norm(x0, axis=1, keepdims=True)
        res = minimize(_energy_and_grad, x0.ravel(), args=(n_free, pull), jac=True, method="L-BFGS-B",
                       options={"maxiter": 2000, "gtol": 1e-9})
        if res.fun < best_e:
            best, best_e = res.x.reshape(n_free, 3), float(res.fun)
    assert best is not None
    best = best * (ratio / float(np.mean(np.linalg.norm(best, axis=1))))
    return np.vstack([np.zeros((1, 3)), best])


@lru_cache(maxsize=16)
def _cached(n_points: int, seed: int) -> np.ndarray:
    pts = optimise_disposition(n_points, seed)
    pts.setflags(write=False)
    return pts


def kernel_points(n_points: int = 15, radius: float = 1.0, seed: int = 0) -> np.ndarray:
    """The project's kernel disposition scaled by ``radius``: (n_points, 3) float32, row 0 = centre."""
    return (_cached(int(n_points), int(seed)) * float(radius)).astype(np.float32)
