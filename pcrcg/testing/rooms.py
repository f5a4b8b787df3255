"""The one box room of the fixtures (tests and benchmarks; tiny data, never used by a run)."""

from __future__ import annotations

import numpy as np


def box_room(rng: np.random.Generator, n_points: int = 30000, size=(4.0, 3.0, 2.5), n_boxes: int = 6,
             density: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) float64 (metres, z up, the room ``[0, size]``) and colors (N, 3) in [0, 1] of a room
    with ``n_boxes`` random boxes on the floor; colors vary smoothly with position.

    Drawn: the floor and the walls x = 0, y = 0, x = L (the wall y = W and the ceiling are left open),
    about 70 % of ``n_points``; the tops and three sides of the boxes, 30 %. ``density`` (points per
    m^2 of the room's floor and walls) sets ``n_points`` instead. The same ``rng`` draws give the same
    room: RANSAC's recorded test results (``tests/test_ransac_fastpath.py``) depend on it.
    """
    L, W, H = size

    def plane(o, u, v, n):
        s = rng.random((n, 2))
        return np.asarray(o, float) + s[:, :1] * np.asarray(u, float) + s[:, 1:] * np.asarray(v, float)

    # the shares of the floor and of the five walls' areas; the open wall y = W's share is not drawn
    area = np.array([L * W, L * H, W * H, W * H, L * H])
    if density is not None:
        n_points = int(round(density * area.sum() / 0.7))  # the drawn planes get 0.7 n_points area / area.sum()
    counts = np.maximum((0.7 * n_points * area / area.sum()).astype(int), 10)
    parts = [plane([0, 0, 0], [L, 0, 0], [0, W, 0], counts[0]), plane([0, 0, 0], [L, 0, 0], [0, 0, H], counts[1]),
             plane([0, 0, 0], [0, W, 0], [0, 0, H], counts[2]), plane([L, 0, 0], [0, W, 0], [0, 0, H], counts[3])]
    per_box = max(int(0.3 * n_points / max(n_boxes, 1) / 3), 10)
    for _ in range(n_boxes):
        c = rng.uniform([0.3, 0.3, 0.0], [L - 1.0, W - 1.0, 0.0])
        e = rng.uniform(0.3, 0.9, 3)
        parts += [plane(c + [0, 0, e[2]], [e[0], 0, 0], [0, e[1], 0], per_box),
                  plane(c, [e[0], 0, 0], [0, 0, e[2]], per_box), plane(c, [0, e[1], 0], [0, 0, e[2]], per_box),
                  plane(c + [e[0], 0, 0], [0, e[1], 0], [0, 0, e[2]], per_box)]
    pts = np.concatenate(parts)
    f = rng.normal(size=(3, 3)) * 4.0
    colors = 0.5 + 0.5 * np.sin(pts @ f + rng.uniform(0, 6, 3))
    return pts, np.clip(colors, 0, 1)
