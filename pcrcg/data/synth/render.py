"""Ray-cast RGB-D rendering of a :class:`Room` with a Kinect-like depth sensor model.

* Color: procedural albedo x Lambertian shading (ambient + point lights with inverse-square
  falloff; the strongest light casts shadows), per-frame exposure gain and light flicker, sRGB gamma, sensor noise.
* Depth: the z of the first hit, plus noise growing with distance
  (sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m, the axial model of Nguyen et al. 2012 for the Kinect),
  holes at grazing angles, outside the sensor range, at depth discontinuities and a few at random.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from pcrcg.data.synth.scene import Room


@dataclass
class SensorModel:
    min_depth: float = 0.4
    max_depth: float = 4.5
    grazing_cos: float = 0.12  # below this |cos(incidence)| the pixel has no depth
    grazing_soft: float = 0.25  # between grazing_cos and this, holes appear with growing probability
    edge_jump: float = 0.08  # metres; pixels at larger depth jumps may be dropped
    edge_drop: float = 0.6
    dropout: float = 0.005
    noise_scale: float = 1.0
    color_noise: float = 2.0 / 255.0


class RoomRenderer:
    """Holds the ray-casting scene of one room; ``render`` draws one RGB-D frame."""

    def __init__(self, room: Room, sensor: SensorModel | None = None):
        self.room = room
        self.sensor = sensor or SensorModel()
        verts, tris = room.mesh_arrays()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(verts)
        mesh.triangle.indices = o3d.core.Tensor(tris)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)
        self.origins = np.stack([p.origin for p in room.panels])
        ax_u = np.stack([p.axis_u for p in room.panels])
        ax_v = np.stack([p.axis_v for p in room.panels])
        self.unit_u = ax_u / np.linalg.norm(ax_u, axis=1, keepdims=True)
        self.unit_v = ax_v / np.linalg.norm(ax_v, axis=1, keepdims=True)
        self.normals = np.stack([p.normal for p in room.panels])

    def render(
        self,
        pose: np.ndarray,
        K: np.ndarray,
        width: int,
        height: int,
        rng: np.random.Generator,
        exposure: float = 1.0,
        light_gain: np.ndarray | None = None,
        shadows: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render a frame from a camera-to-world ``pose`` (4x4) with intrinsics ``K`` (3x3).

        Returns color (H, W, 3) uint8, noisy depth (H, W) float32 metres (0 = hole) and the
        noise-free depth (H, W) float32 (0 = no hit).
        """
        H, W = height, width
        d_cam = self._directions(K, W, H)
        R, t = pose[:3, :3], pose[:3, 3]
        d_world = d_cam @ R.T
        rays = np.concatenate([np.broadcast_to(t, d_world.shape), d_world], 1).astype(np.float32)
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        z = hit["t_hit"].numpy().astype(np.float64)  # ray direction has unit z in the camera frame
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        valid = np.isfinite(z) & (prim >= 0) & (prim < 2 * len(self.room.panels))
        z = np.where(valid, z, 0.0)
        panel = np.where(valid, prim // 2, 0)

        f32 = np.float32
        pts = (t + d_world * z[:, None]).astype(f32)
        rel = pts - self.origins[panel].astype(f32)
        su = np.einsum("ij,ij->i", rel, self.unit_u[panel].astype(f32))
        sv = np.einsum("ij,ij->i", rel, self.unit_v[panel].astype(f32))
        albedo = np.zeros((len(z), 3), f32)
        vidx = np.nonzero(valid)[0]
        order = vidx[np.argsort(panel[vidx], kind="stable")]
        ids, starts = np.unique(panel[order], return_index=True)
        for p_id, idx in zip(ids, np.split(order, starts[1:])):  # one texture call per visible panel
            albedo[idx] = self.room.panels[p_id].texture(su[idx], sv[idx])

        n = self.normals[panel].astype(f32)
        cos_view = np.einsum("ij,ij->i", n, d_world.astype(f32)) / np.linalg.norm(d_world, axis=1).astype(f32)
        n *= np.where(cos_view > 0, -1.0, 1.0).astype(f32)[:, None]  # face the camera
        shade = np.full(len(z), self.room.ambient, f32)
        gains = np.ones(len(self.room.lights)) if light_gain is None else light_gain
        strongest = int(np.argmax(self.room.light_power)) if len(self.room.lights) else -1
        for li, (L, power, g) in enumerate(zip(self.room.lights, self.room.light_power, gains)):
            to_l = L.astype(f32) - pts
            dist = np.sqrt(np.einsum("ij,ij->i", to_l, to_l))
            ldir = to_l / np.maximum(dist, 1e-6)[:, None]
            lam = np.maximum(np.einsum("ij,ij->i", n, ldir), 0)
            contrib = f32(g * power) * lam / (1.0 + 0.15 * dist**2)
            if shadows and li == strongest:  # cast shadows of the main light only (one ray per pixel)
                idx = np.nonzero(valid & (lam > 0))[0]
                if len(idx):
                    srays = np.concatenate([pts[idx] + n[idx] * f32(2e-3), ldir[idx]], 1)
                    t_occ = self.scene.cast_rays(o3d.core.Tensor(srays))["t_hit"].numpy()
                    contrib[idx[t_occ < dist[idx] - 0.01]] *= 0.15
            shade += contrib
        linear = albedo * shade[:, None] * exposure
        s = self.sensor
        color = np.clip(linear, 0, 1) ** (1 / 2.2)
        color = color + s.color_noise * rng.standard_normal(size=color.shape, dtype=np.float32)
        color[~valid] = 0.0
        color_u8 = np.clip(np.round(color * 255), 0, 255).astype(np.uint8).reshape(H, W, 3)

        clean = z.reshape(H, W).astype(np.float32)
        depth = self._sensor_depth(clean, np.abs(cos_view).reshape(H, W), valid.reshape(H, W), rng)
        return color_u8, depth, clean

    def _directions(self, K: np.ndarray, W: int, H: int) -> np.ndarray:
        """Camera-frame ray directions (H*W, 3) with unit z, cached per intrinsics and size."""
        key = (W, H, *np.round(K.ravel(), 6))
        cached = getattr(self, "_dir_cache", None)
        if cached is None or cached[0] != key:
            u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
            self._dir_cache = (key, d)
        return self._dir_cache[1]

    def _sensor_depth(self, z: np.ndarray, cos_inc: np.ndarray, valid: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        s = self.sensor
        sigma = (0.0012 + 0.0019 * (z - 0.4) ** 2) * s.noise_scale
        d = z + rng.normal(size=z.shape) * sigma
        keep = valid & (z >= s.min_depth) & (z <= s.max_depth)
        keep &= cos_inc >= s.grazing_cos
        soft = np.clip((s.grazing_soft - cos_inc) / (s.grazing_soft - s.grazing_cos), 0, 1)
        keep &= rng.random(z.shape) >= 0.6 * soft
        jump = np.zeros_like(z, dtype=bool)
        dz_x = np.abs(np.diff(z, axis=1)) > s.edge_jump
        dz_y = np.abs(np.diff(z, axis=0)) > s.edge_jump
        jump[:, 1:] |= dz_x
        jump[:, :-1] |= dz_x
        jump[1:, :] |= dz_y
        jump[:-1, :] |= dz_y
        keep &= ~(jump & (rng.random(z.shape) < s.edge_drop))
        keep &= rng.random(z.shape) >= s.dropout
        return np.where(keep, d, 0.0).astype(np.float32)
