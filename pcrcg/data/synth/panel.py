"""The surface elements of a generated room: textured parallelograms and triangles ("panels")."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcrcg.data.synth.textures import Texture


@dataclass
class Panel:
    """A textured parallelogram ``origin + s * axis_u + t * axis_v`` for s, t in [0, 1], or, with
    ``tri``, the triangle s, t >= 0, s + t <= 1. The texture is evaluated at the point's
    coordinates (metres) along the unit axes."""

    origin: np.ndarray  # (3,)
    axis_u: np.ndarray  # (3,) edge vector (length = width)
    axis_v: np.ndarray  # (3,) edge vector (length = height)
    texture: Texture
    kind: str
    tri: bool = False

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.axis_u, self.axis_v)
        return n / max(float(np.linalg.norm(n)), 1e-12)


@dataclass
class Room:
    """A generated room: its panels, lights and where the camera may walk.

    ``size`` is the bounding box (W, D, H) of the room, which spans [0, W] x [0, D] x [0, H];
    ``walkable`` is a boolean grid of cells (``cell`` metres, index [ix, iy]) where a person can
    stand: inside the floor plan and away from walls and furniture.
    """

    size: np.ndarray  # (3,) W, D, H
    panels: list[Panel] = field(default_factory=list)
    lights: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (L, 3) positions
    light_power: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (L,)
    ambient: float = 0.3
    keepout: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # boxes (min, max)
    walkable: np.ndarray | None = None  # (GX, GY) bool
    cell: float = 0.1
    focus: np.ndarray | None = None  # (2,) the middle of the room's central furniture, if any
    room_type: str = "room"

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vertices (V, 3) float32, triangles (T, 3) int32 and each triangle's panel index (T,)."""
        verts, tris, owner = [], [], []
        for p, pan in enumerate(self.panels):
            o, a, b = pan.origin, pan.axis_u, pan.axis_v
            k = len(verts)
            if pan.tri:
                verts += [o, o + a, o + b]
                tris.append([k, k + 1, k + 2])
                owner.append(p)
            else:
                verts += [o, o + a, o + a + b, o + b]
                tris += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
                owner += [p, p]
        return np.asarray(verts, np.float32), np.asarray(tris, np.int32), np.asarray(owner, np.int64)

    def is_walkable(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool for points (N, 2); everything outside the grid is not walkable."""
        xy = np.atleast_2d(xy)
        if self.walkable is None:
            W, D = self.size[:2]
            return (xy[:, 0] > 0.8) & (xy[:, 0] < W - 0.8) & (xy[:, 1] > 0.8) & (xy[:, 1] < D - 0.8)
        idx = np.floor(xy / self.cell).astype(np.int64)
        gx, gy = self.walkable.shape
        inside = (idx[:, 0] >= 0) & (idx[:, 0] < gx) & (idx[:, 1] >= 0) & (idx[:, 1] < gy)
        out = np.zeros(len(xy), bool)
        out[inside] = self.walkable[idx[inside, 0], idx[inside, 1]]
        return out
