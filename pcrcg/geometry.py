"""Small rigid-geometry helpers shared by every stage (NumPy, float64 unless noted)."""

from __future__ import annotations

import numpy as np


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points; keeps the input dtype."""
    T = np.asarray(T)
    out = pts @ T[:3, :3].T.astype(pts.dtype) + T[:3, 3].astype(pts.dtype)
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x for v (3,), or (N, 3, 3) for v (N, 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def axis_angle_to_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    K = skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def random_rotation(rng: np.random.Generator, max_angle: float = np.pi) -> np.ndarray:
    """A rotation about a uniformly random axis by an angle uniform in [0, max_angle]."""
    axis = rng.normal(size=3)
    return axis_angle_to_matrix(axis, rng.uniform(0.0, max_angle))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Geodesic angle of a rotation matrix, degrees."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """Camera-to-world 4x4 of a camera at ``eye`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-8:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    if roll:
        R = R @ axis_angle_to_matrix([0, 0, 1], roll)
    return make_transform(R, eye)


def backproject(depth: np.ndarray, K: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) metres -> camera-frame points (M, 3) and their pixel indices (M, 2) as (v, u).

    Pixels with depth 0 are skipped. ``stride`` subsamples the pixel grid.
    """
    d = depth[::stride, ::stride]
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    v = v * stride
    u = u * stride
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1), np.stack([v, u], axis=1)


def project(pts_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> pixel coordinates (N, 2) as (u, v) floats, and depth (N,)."""
    z = pts_cam[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * pts_cam[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pts_cam[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy), pixel-centre convention."""
    K2 = np.array(K, dtype=np.float64)
    K2[0, 0] *= sx
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 1] *= sy
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2
