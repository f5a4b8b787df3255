"""Ray-cast RGB-D rendering of a :class:`Room` with a Kinect-like depth sensor model.

* Color: albedo (procedural materials and printed pictures) x Lambertian shading (ambient + point
  lights with inverse-square falloff; the strongest light casts shadows; windows glow), then the
  camera (:meth:`RoomRenderer.expose`): exposure gain (driven by an auto-exposure loop in the
  caller), light flicker, motion blur along the image motion during the exposure, vignetting,
  shot and read noise, sRGB gamma, 8-bit quantisation and JPEG compression like a consumer sensor.
* Depth: the z of the first hit, plus noise growing with distance
  (sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m, the axial model of Nguyen et al. 2012 for the Kinect),
  holes at grazing angles, outside the sensor range, at depth discontinuities and a few at random.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pcrcg.data.synth.panel import Room


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
    shot_noise: float = 0.0  # variance per unit of linear signal (photon noise)
    vignetting: float = 0.0  # relative fall-off at the image corners
    jpeg_quality: int = 0  # 0: no compression
    exposure_time: float = 0.0  # seconds the shutter is open (motion blur); 0: none
    dark_drop: float = 0.0  # hole probability on black surfaces (albedo -> 0)
    dark_albedo: float = 0.08  # albedo luminance below which holes start


@dataclass
class Radiance:
    """One ray-cast view: linear radiance (H, W, 3) float32 before the camera, noise-free depth
    (H, W) float32 (0 = no hit or a window), |cos(incidence)| (H, W), the depth-bearing hits
    (H, W) bool and the albedo's luminance (H, W)."""

    linear: np.ndarray
    depth: np.ndarray
    cos_inc: np.ndarray
    valid: np.ndarray
    albedo: np.ndarray


class RoomRenderer:
    """Holds the ray-casting scene of one room; ``render`` draws one RGB-D frame."""

    def __init__(self, room: Room, sensor: SensorModel | None = None):
        self.room = room
        self.sensor = sensor or SensorModel()
        import open3d as o3d  # here, not at the top: what reads data sets (a run) needs no Open3D

        verts, tris, self.owner = room.mesh_arrays()
        self._tensor = o3d.core.Tensor
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(verts)
        mesh.triangle.indices = o3d.core.Tensor(tris)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(mesh)
        self.origins = np.stack([p.origin for p in room.panels])
        ax_u = np.stack([p.axis_u for p in room.panels])
        ax_v = np.stack([p.axis_v for p in room.panels])
        self.unit_u = ax_u / np.maximum(np.linalg.norm(ax_u, axis=1, keepdims=True), 1e-12)
        self.unit_v = ax_v / np.maximum(np.linalg.norm(ax_v, axis=1, keepdims=True), 1e-12)
        self.normals = np.stack([p.normal for p in room.panels])
        tex_ids: dict[int, int] = {}
        self.textures = []
        for p in room.panels:
            if id(p.texture) not in tex_ids:
                tex_ids[id(p.texture)] = len(self.textures)
                self.textures.append(p.texture)
        self.panel_tex = np.array([tex_ids[id(p.texture)] for p in room.panels], np.int64)
        self.sky = np.array([p.kind == "sky" for p in room.panels])

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
        blur_px: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render a frame from a camera-to-world ``pose`` (4x4) with intrinsics ``K`` (3x3).

        ``blur_px`` (2,) is the image motion (pixels) during the exposure. Returns color (H, W, 3)
        uint8, noisy depth (H, W) float32 metres (0 = hole) and the noise-free depth (H, W) float32
        (0 = no hit).
        """
        rad = self.radiance(pose, K, width, height, light_gain, shadows)
        color = self.expose(rad.linear, exposure, rng, blur_px)
        return color, self.sensor_depth(rad, rng), rad.depth

    def radiance(
        self, pose: np.ndarray, K: np.ndarray, width: int, height: int,
        light_gain: np.ndarray | None = None, shadows: bool = True,
    ) -> "Radiance":
        """What reaches the camera and the depth sensor from a camera-to-world ``pose``."""
        H, W = height, width
        d_cam = self._directions(K, W, H)
        R, t = pose[:3, :3], pose[:3, 3]
        d_world = d_cam @ R.T
        rays = np.concatenate([np.broadcast_to(t, d_world.shape), d_world], 1).astype(np.float32)
        hit = self.scene.cast_rays(self._tensor(rays))
        z = hit["t_hit"].numpy().astype(np.float64)  # ray direction has unit z in the camera frame
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        valid = np.isfinite(z) & (prim >= 0) & (prim < len(self.owner))
        z = np.where(valid, z, 0.0)
        panel = np.where(valid, self.owner[np.clip(prim, 0, len(self.owner) - 1)], 0)

        f32 = np.float32
        pts = (t + d_world * z[:, None]).astype(f32)
        rel = pts - self.origins[panel].astype(f32)
        su = np.einsum("ij,ij->i", rel, self.unit_u[panel].astype(f32))
        sv = np.einsum("ij,ij->i", rel, self.unit_v[panel].astype(f32))
        albedo = np.zeros((len(z), 3), f32)
        vidx = np.nonzero(valid)[0]
        tex = self.panel_tex[panel[vidx]]
        order = vidx[np.argsort(tex, kind="stable")]
        ids, starts = np.unique(self.panel_tex[panel[order]], return_index=True)
        for t_id, idx in zip(ids, np.split(order, starts[1:])):  # one texture call per visible texture
            albedo[idx] = self.textures[t_id](su[idx], sv[idx])

        lum = albedo @ np.array([0.3, 0.59, 0.11], f32)  # of the printed (sRGB) colour: dark_albedo's scale
        albedo = albedo**f32(2.2)  # textures are specified as sRGB colours; light adds up linearly
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
                    t_occ = self.scene.cast_rays(self._tensor(srays))["t_hit"].numpy()
                    contrib[idx[t_occ < dist[idx] - 0.01]] *= 0.15
            shade += contrib
        sky = valid & self.sky[panel]
        shade[sky] = 2.5  # windows: bright, washed out
        linear = albedo * shade[:, None]
        linear[~valid] = 0.0
        valid &= ~sky  # no depth through glass
        clean = np.where(valid, z, 0.0).reshape(H, W).astype(np.float32)
        return Radiance(linear.reshape(H, W, 3), clean, np.abs(cos_view).reshape(H, W), valid.reshape(H, W),
                        lum.reshape(H, W))

    def expose(self, linear: np.ndarray, exposure: float, rng: np.random.Generator,
               blur_px: np.ndarray | None = None) -> np.ndarray:
        """The camera: linear radiance (H, W, 3) -> an 8-bit sRGB image (H, W, 3) uint8."""
        import cv2

        s = self.sensor
        H, W = linear.shape[:2]
        img = linear * np.float32(exposure)
        if blur_px is not None:
            img = motion_blur(img, np.asarray(blur_px, float))
        if s.vignetting > 0:
            yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
            r2 = ((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2
            img = img * (1.0 - s.vignetting * r2 / 2.0)[:, :, None]
        img = np.clip(img, 0, 1)
        if s.shot_noise > 0:
            img = img + np.sqrt(s.shot_noise * img) * rng.standard_normal(size=img.shape, dtype=np.float32)
        color = np.clip(img, 0, 1) ** (1 / 2.2)
        color = color + s.color_noise * rng.standard_normal(size=color.shape, dtype=np.float32)
        color_u8 = np.clip(np.round(color * 255), 0, 255).astype(np.uint8)
        if s.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(color_u8[:, :, ::-1]),
                                   [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
            color_u8 = np.ascontiguousarray(cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1])
        return color_u8

    def _directions(self, K: np.ndarray, W: int, H: int) -> np.ndarray:
        """Camera-frame ray directions (H*W, 3) with unit z, cached per intrinsics and size."""
        key = (W, H, *np.round(K.ravel(), 6))
        cached = getattr(self, "_dir_cache", None)
        if cached is None or cached[0] != key:
            u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
            d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
            self._dir_cache = (key, d)
        return self._dir_cache[1]

    def image_motion(self, pose0: np.ndarray, pose1: np.ndarray, K: np.ndarray, clean: np.ndarray) -> np.ndarray:
        """Median image motion (2,) in pixels of the frame's visible points between two camera
        poses (camera-to-world 4x4): the blur a shutter open from pose0 to pose1 leaves."""
        H, W = clean.shape
        ys, xs = np.mgrid[0:H:8, 0:W:8]
        z = clean[ys, xs].ravel()
        ok = z > 0
        if not ok.any():
            return np.zeros(2)
        uv = np.stack([xs.ravel()[ok], ys.ravel()[ok]], 1).astype(np.float64)
        p = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(uv))], 1) * z[ok, None]
        T = np.linalg.inv(pose1) @ pose0
        q = p @ T[:3, :3].T + T[:3, 3]
        q = q[:, :2] / np.maximum(q[:, 2:], 1e-3)
        uv1 = np.stack([q[:, 0] * K[0, 0] + K[0, 2], q[:, 1] * K[1, 1] + K[1, 2]], 1)
        return np.median(uv1 - uv, axis=0)

    def sensor_depth(self, rad: "Radiance", rng: np.random.Generator) -> np.ndarray:
        """Kinect-like depth (H, W) float32 metres (0 = hole) of a :class:`Radiance`."""
        depth = self._sensor_depth(rad.depth, rad.cos_inc, rad.valid, rng)
        s = self.sensor
        if s.dark_drop > 0:  # dark, light-absorbing surfaces return no infrared pattern
            p = s.dark_drop * np.clip((s.dark_albedo - rad.albedo) / s.dark_albedo, 0, 1)
            depth[rng.random(depth.shape) < p] = 0.0
        return depth

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


def motion_blur(img: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Blur an (H, W, C) float image along a straight image motion (2,) pixels (a box kernel
    along the segment, the exposure's average)."""
    import cv2

    length = float(np.hypot(*motion))
    if length < 0.75:
        return img
    n = int(np.ceil(length)) | 1
    k = np.zeros((n, n), np.float32)
    c = n // 2
    steps = max(2, int(np.ceil(length * 2)))
    for a in np.linspace(-0.5, 0.5, steps):
        x, y = c + a * motion[0], c + a * motion[1]
        k[int(round(np.clip(y, 0, n - 1))), int(round(np.clip(x, 0, n - 1)))] += 1.0
    k /= k.sum()
    return cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REPLICATE)
