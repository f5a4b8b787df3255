"""Classical baselines on the same pairs: FPFH + RANSAC, ICP, colored ICP, SIFT-DLT, lifted SIFT.

* ``fpfh``: Open3D FPFH descriptors on a voxel-downsampled cloud, nearest-neighbour matching
  (mutual by default) and our RANSAC (Open3D's settings; the threshold scales with the voxel).
* ``icp``: Open3D point-to-plane ICP, from the identity or from a given initial estimate.
* ``color_icp``: Open3D colored ICP (Park et al. 2017), coarse to fine over three voxel sizes
  as in Open3D's tutorial, from the identity or from a given estimate; needs colors.
* ``sift_dlt``: the paper's SIFT-DLT row, a relative pose from the images alone: OpenCV SIFT matches
  between a view of each fragment (:func:`pcrcg.vision.matching.match_images`), the essential matrix
  (RANSAC on the normalised image points) and the pose it holds (``recoverPose``: a rotation and a
  unit translation), the translation's scale from depth (the median ratio of the depth maps' depth to
  the triangulated depth of the inlier matches); of several view pairs the one with the most inliers.
* ``sift_lifted``: SIFT matches of every view pair lifted to 3D with depth and the views' poses, and
  a rigid transform fitted to the 3D-3D matches (RANSAC over 3-point Kabsch fits, least-squares
  refits): not a method of the paper (this project's first reading of its SIFT-DLT row).

All return a :class:`BaselineResult` whose ``transform`` (4, 4) maps source into target.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field, fields
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from pcrcg.errors import ConfigError
from pcrcg.registration.matching import match_descriptors
from pcrcg.registration.ransac import RansacConfig, ransac

METHODS = ("fpfh", "icp", "color_icp", "sift_dlt", "sift_lifted")
SIFT_METHODS = ("sift_dlt", "sift_lifted")  # the methods that read the fragments' RGB-D views


def _from_dict(cls, d: Mapping | None, where: str):
    if d is None:
        return cls()
    if isinstance(d, cls):
        return d
    names = {f.name for f in fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ConfigError(where, sorted(unknown), f"keys among {sorted(names)}")
    kw = {}
    for k, v in dict(d).items():
        kw[k] = tuple(v) if isinstance(v, (list, tuple)) or type(v).__name__ == "ListConfig" else v
    return cls(**kw)


@dataclass
class FpfhConfig:
    """FPFH + RANSAC. Radii are multiples of ``voxel`` (Open3D's global-registration recipe)."""

    voxel: float = 0.05
    normal_radius: float = 2.0  # x voxel
    feature_radius: float = 5.0  # x voxel
    max_nn_normal: int = 30
    max_nn_feature: int = 100
    mutual: bool = True
    distance: float = 1.5  # x voxel: RANSAC inlier threshold

    def __post_init__(self) -> None:
        if self.voxel <= 0:
            raise ConfigError("registration.fpfh.voxel", self.voxel, "> 0 (metres)")


@dataclass
class IcpConfig:
    """Point-to-plane ICP on a voxel-downsampled pair."""

    voxel: float = 0.025
    distance: float = 0.05  # max correspondence distance, metres
    normal_radius: float = 2.0  # x voxel
    max_iterations: int = 50

    def __post_init__(self) -> None:
        if self.voxel < 0 or self.distance <= 0:
            raise ConfigError("registration.icp", (self.voxel, self.distance), "voxel >= 0 and distance > 0")


@dataclass
class ColorIcpConfig:
    """Colored ICP, coarse to fine (Open3D tutorial's schedule); distance = voxel at each scale."""

    voxels: tuple[float, ...] = (0.04, 0.02, 0.01)
    iterations: tuple[int, ...] = (50, 30, 14)
    lambda_geometric: float = 0.968
    normal_radius: float = 2.0  # x voxel

    def __post_init__(self) -> None:
        self.voxels = tuple(float(v) for v in self.voxels)
        self.iterations = tuple(int(v) for v in self.iterations)
        if len(self.voxels) != len(self.iterations) or not self.voxels or min(self.voxels) <= 0:
            raise ConfigError("registration.color_icp", (self.voxels, self.iterations),
                              "voxels > 0 and iterations of the same, non-zero length")


@dataclass
class SiftLiftedConfig:
    """Lifted SIFT: 2D matches lifted with depth, robust rigid fit.

    view_pairs: ``all`` (every src view with every tgt view) or ``paper`` (first-first, ...);
    matcher: keyword arguments of :class:`pcrcg.vision.matching.MatcherConfig`;
    distance: RANSAC inlier threshold (metres); refine: least-squares refits on the inliers;
    depth_min / depth_max: depth range (metres) that is trusted.
    """

    view_pairs: str = "all"
    matcher: dict = field(default_factory=lambda: {"method": "sift", "ratio": 0.8, "mutual": True})
    distance: float = 0.05
    refine: int = 3
    depth_min: float = 0.1
    depth_max: float = 6.0

    def __post_init__(self) -> None:
        if self.view_pairs not in ("all", "paper"):
            raise ConfigError("registration.sift_lifted.view_pairs", self.view_pairs, "all | paper")
        self.matcher = dict(self.matcher or {})


@dataclass
class SiftDltConfig:
    """SIFT-DLT (the paper's): relative pose from the images, scale from depth.

    view_pairs: ``all`` | ``paper`` (as :class:`SiftLiftedConfig`; the pair with the most pose inliers
    is used); matcher: :class:`pcrcg.vision.matching.MatcherConfig` keywords; threshold: the essential
    matrix RANSAC's threshold in pixels (of the view's image); confidence: its confidence;
    min_inliers: fewer pose inliers with depth give the identity; refine: the pose refined on the
    inliers (robust least squares of the Sampson distances; false: RANSAC's best model as is);
    depth_min / depth_max (metres).
    """

    view_pairs: str = "all"
    matcher: dict = field(default_factory=lambda: {"method": "sift", "ratio": 0.8, "mutual": True})
    threshold: float = 1.0
    confidence: float = 0.999
    min_inliers: int = 8
    refine: bool = True
    depth_min: float = 0.1
    depth_max: float = 6.0

    def __post_init__(self) -> None:
        if self.view_pairs not in ("all", "paper"):
            raise ConfigError("registration.sift_dlt.view_pairs", self.view_pairs, "all | paper")
        if not self.threshold > 0:
            raise ConfigError("registration.sift_dlt.threshold", self.threshold, "> 0 (pixels)")
        if not 0 < self.confidence < 1:
            raise ConfigError("registration.sift_dlt.confidence", self.confidence, "in (0, 1)")
        self.matcher = dict(self.matcher or {})


@dataclass
class BaselineConfig:
    """All baselines' settings (the ``fpfh``/``icp``/``color_icp``/``sift_dlt``/``sift_lifted`` sub-nodes
    of the ``registration`` config group) and the protocol's RANSAC."""

    fpfh: FpfhConfig = field(default_factory=FpfhConfig)
    icp: IcpConfig = field(default_factory=IcpConfig)
    color_icp: ColorIcpConfig = field(default_factory=ColorIcpConfig)
    sift_dlt: SiftDltConfig = field(default_factory=SiftDltConfig)
    sift_lifted: SiftLiftedConfig = field(default_factory=SiftLiftedConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    device: str = "cpu"

    @classmethod
    def from_dict(cls, d: Mapping | None) -> "BaselineConfig":
        d = dict(d or {})
        kw: dict[str, Any] = {}
        for name, sub in (("fpfh", FpfhConfig), ("icp", IcpConfig), ("color_icp", ColorIcpConfig),
                          ("sift_dlt", SiftDltConfig), ("sift_lifted", SiftLiftedConfig)):
            if d.get(name) is not None:
                node = dict(d[name])
                if name in SIFT_METHODS and "matcher" in node:
                    node["matcher"] = dict(node["matcher"] or {})
                kw[name] = _from_dict(sub, node, f"registration.{name}")
        if d.get("ransac") is not None:
            kw["ransac"] = RansacConfig.from_dict(dict(d["ransac"]))
        if d.get("device"):
            kw["device"] = str(d["device"])
        return cls(**kw)


@dataclass
class BaselineResult:
    """transform (4, 4) maps source into target; ``correspondences`` (K, 2) and the matched
    points (K, 3) in each frame when the method matches features (fpfh, sift_dlt), else None."""

    transform: np.ndarray
    fitness: float = float("nan")
    inlier_rmse: float = float("nan")
    src_corr: np.ndarray | None = None
    tgt_corr: np.ndarray | None = None
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- Open3D helpers


def _cloud(points: np.ndarray, colors: np.ndarray | None = None):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors, dtype=np.float64), 0.0, 1.0))
    return pcd


def _down(pcd, voxel: float):
    return pcd.voxel_down_sample(voxel) if voxel > 0 else pcd


def _normals(pcd, radius: float, max_nn: int = 30) -> None:
    import open3d as o3d

    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))


def _init(init: np.ndarray | None) -> np.ndarray:
    if init is None:
        return np.eye(4)
    T = np.asarray(init, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"initial transform must be 4x4, got {T.shape}")
    return T


# --------------------------------------------------------------------------- FPFH


def fpfh_features(points: np.ndarray, cfg: FpfhConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-downsample and describe: points (N, 3) -> (M, 3) float64 points, (M, 33) float32 FPFH."""
    import open3d as o3d

    cfg = cfg or FpfhConfig()
    pcd = _down(_cloud(points), cfg.voxel)
    _normals(pcd, cfg.normal_radius * cfg.voxel, cfg.max_nn_normal)
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.feature_radius * cfg.voxel, max_nn=cfg.max_nn_feature)
    )
    return np.asarray(pcd.points), np.asarray(f.data, dtype=np.float32).T.copy()


def register_fpfh(
    src_points: np.ndarray, tgt_points: np.ndarray, cfg: BaselineConfig | None = None, seed: int = 0
) -> BaselineResult:
    """FPFH + RANSAC (our batched RANSAC with the protocol's checkers and iterations)."""
    cfg = cfg or BaselineConfig()
    sp, sf = fpfh_features(src_points, cfg.fpfh)
    tp, tf = fpfh_features(tgt_points, cfg.fpfh)
    corr = match_descriptors(sf, tf, mutual=cfg.fpfh.mutual, device=cfg.device)
    if cfg.fpfh.mutual and len(corr) < 3 * cfg.ransac.ransac_n:
        corr = match_descriptors(sf, tf, mutual=False, device=cfg.device)
    rc = dataclasses.replace(cfg.ransac, distance=cfg.fpfh.distance * cfg.fpfh.voxel)
    res = ransac(sp, tp, corr, rc, seed=seed, device=cfg.device)
    return BaselineResult(res.transform, res.fitness, res.inlier_rmse, sp[corr[:, 0]], tp[corr[:, 1]],
                          {"n_correspondences": int(len(corr)), "iterations": res.iterations})


# --------------------------------------------------------------------------- ICP


def register_icp(
    src_points: np.ndarray, tgt_points: np.ndarray, init: np.ndarray | None = None, cfg: IcpConfig | None = None
) -> BaselineResult:
    """Point-to-plane ICP (Open3D) from ``init`` (identity by default)."""
    import open3d as o3d

    cfg = cfg or IcpConfig()
    reg = o3d.pipelines.registration
    src, tgt = _down(_cloud(src_points), cfg.voxel), _down(_cloud(tgt_points), cfg.voxel)
    radius = cfg.normal_radius * (cfg.voxel if cfg.voxel > 0 else cfg.distance / 2)
    _normals(tgt, radius)
    res = reg.registration_icp(
        src, tgt, cfg.distance, _init(init), reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=cfg.max_iterations),
    )
    return BaselineResult(np.asarray(res.transformation).copy(), float(res.fitness), float(res.inlier_rmse))


def register_color_icp(
    src_points: np.ndarray,
    src_colors: np.ndarray | None,
    tgt_points: np.ndarray,
    tgt_colors: np.ndarray | None,
    init: np.ndarray | None = None,
    cfg: ColorIcpConfig | None = None,
) -> BaselineResult:
    """Colored ICP (Open3D), coarse to fine, from ``init``. Colors (N, 3) in [0, 1] are required."""
    import open3d as o3d

    cfg = cfg or ColorIcpConfig()
    if src_colors is None or tgt_colors is None:
        raise ValueError("color_icp needs colors on both clouds (the source or target file has none)")
    reg = o3d.pipelines.registration
    src_full, tgt_full = _cloud(src_points, src_colors), _cloud(tgt_points, tgt_colors)
    T = _init(init)
    res = None
    for voxel, iters in zip(cfg.voxels, cfg.iterations):
        src, tgt = _down(src_full, voxel), _down(tgt_full, voxel)
        _normals(src, cfg.normal_radius * voxel)
        _normals(tgt, cfg.normal_radius * voxel)
        if len(src.points) < 10 or len(tgt.points) < 10:
            continue
        try:
            res = reg.registration_colored_icp(
                src, tgt, voxel, T, reg.TransformationEstimationForColoredICP(lambda_geometric=cfg.lambda_geometric),
                reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=iters),
            )
        except RuntimeError:  # no correspondences at this scale: keep the current estimate
            continue
        T = np.asarray(res.transformation).copy()
    fit = float(res.fitness) if res is not None else 0.0
    rmse = float(res.inlier_rmse) if res is not None else float("nan")
    return BaselineResult(T, fit, rmse)


# --------------------------------------------------------------------------- SIFT: lifted and DLT


def lift_pixels(uv: np.ndarray, view: Any, depth_min: float = 0.1, depth_max: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (K, 2) as (u, v) of ``view`` -> fragment-frame points (K, 3) float64 and valid (K,) bool.

    Depth is read at the nearest pixel; pixels without depth (0) or outside [depth_min, depth_max]
    are invalid (their points are NaN). ``view`` is a :class:`pcrcg.data.dataset.View`.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    depth = np.asarray(view.depth)
    H, W = depth.shape
    ui = np.rint(uv[:, 0]).astype(np.int64)
    vi = np.rint(uv[:, 1]).astype(np.int64)
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    z = np.zeros(len(uv))
    z[inside] = depth[vi[inside], ui[inside]]
    valid = inside & (z > depth_min) & (z < depth_max)
    K = np.asarray(view.intrinsics, dtype=np.float64)
    x = (uv[:, 0] - K[0, 2]) * z / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) * z / K[1, 1]
    cam = np.stack([x, y, z], 1)
    P = np.asarray(view.pose, dtype=np.float64)
    pts = cam @ P[:3, :3].T + P[:3, 3]
    pts[~valid] = np.nan
    return pts, valid


def _default_matcher(cfg: SiftDltConfig | SiftLiftedConfig) -> Callable[[np.ndarray, np.ndarray], Any]:
    try:
        from pcrcg.vision import matching as vm
    except ImportError as exc:  # pragma: no cover - the vision stage ships with the package
        raise ImportError(f"the SIFT methods need pcrcg.vision.matching (2D SIFT matches): {exc}") from exc
    known = {f.name for f in fields(vm.MatcherConfig)}
    mcfg = vm.MatcherConfig(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in cfg.matcher.items() if k in known})
    return lambda a, b: vm.match_images(a, b, mcfg)


def _view_pairs(n_src: int, n_tgt: int, mode: str) -> list[tuple[int, int]]:
    if mode == "all":
        return list(itertools.product(range(n_src), range(n_tgt)))
    return [(k, k) for k in range(min(n_src, n_tgt))]


def sift_correspondences(
    src_views: Sequence[Any],
    tgt_views: Sequence[Any],
    cfg: SiftLiftedConfig | None = None,
    matcher: Callable[[np.ndarray, np.ndarray], Any] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3D-3D matches from 2D matches of the views: src (K, 3), tgt (K, 3) in the fragments' frames
    and the matches' confidence (K,). ``matcher(img_a, img_b) -> Matches`` (uv_a, uv_b, confidence)."""
    cfg = cfg or SiftLiftedConfig()
    matcher = matcher or _default_matcher(cfg)
    pairs = _view_pairs(len(src_views), len(tgt_views), cfg.view_pairs)
    S, T, C = [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros(0)]
    for a, b in pairs:
        m = matcher(src_views[a].color, tgt_views[b].color)
        if len(m.uv_a) == 0:
            continue
        ps, vs = lift_pixels(m.uv_a, src_views[a], cfg.depth_min, cfg.depth_max)
        pt, vt = lift_pixels(m.uv_b, tgt_views[b], cfg.depth_min, cfg.depth_max)
        ok = vs & vt
        S.append(ps[ok])
        T.append(pt[ok])
        C.append(np.asarray(m.confidence, dtype=np.float64).reshape(-1)[ok])
    return np.concatenate(S), np.concatenate(T), np.concatenate(C)


def register_sift_lifted(
    src_views: Sequence[Any],
    tgt_views: Sequence[Any],
    cfg: BaselineConfig | None = None,
    seed: int = 0,
    matcher: Callable[[np.ndarray, np.ndarray], Any] | None = None,
) -> BaselineResult:
    """Lifted SIFT: robust rigid fit to the lifted 2D matches (identity when fewer than 3 survive)."""
    cfg = cfg or BaselineConfig()
    if not src_views or not tgt_views:
        raise ValueError("sift_lifted needs the RGB-D views of both fragments (none were given)")
    s, t, conf = sift_correspondences(src_views, tgt_views, cfg.sift_lifted, matcher)
    K = len(s)
    if K < 3:
        return BaselineResult(np.eye(4), 0.0, float("nan"), s, t, {"n_correspondences": K})
    rc = dataclasses.replace(cfg.ransac, distance=cfg.sift_lifted.distance, refine=cfg.sift_lifted.refine)
    corr = np.stack([np.arange(K), np.arange(K)], 1)
    res = ransac(s, t, corr, rc, seed=seed, device=cfg.device)
    return BaselineResult(res.transform, res.fitness, res.inlier_rmse, s, t, {"n_correspondences": K})


def _normalised(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) -> normalised image coordinates (n, 2) of a camera with intrinsics K."""
    K = np.asarray(K, dtype=np.float64)
    return np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]], 1)


def _depth_at(view: Any, uv: np.ndarray, depth_min: float, depth_max: float) -> np.ndarray:
    """Depth (n,) at the nearest pixel, NaN where there is none or it is outside the trusted range."""
    depth = np.asarray(view.depth)
    H, W = depth.shape
    u, v = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    z = np.full(len(uv), np.nan)
    z[inside] = depth[v[inside], u[inside]]
    z[~((z > depth_min) & (z < depth_max))] = np.nan
    return z


def _sampson(E: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distances (n,) of normalised point pairs to the epipolar geometry of E."""
    a = np.hstack([xa, np.ones((len(xa), 1))])
    b = np.hstack([xb, np.ones((len(xb), 1))])
    Ea, Etb = a @ E.T, b @ E
    num = np.einsum("ij,ij->i", b, Ea)
    den = np.sqrt(Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2) + 1e-12
    return num / den


def _refine_pose(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, scale: float):
    """R, unit t refined on the inliers: robust least squares of the Sampson distances (RANSAC's best
    minimal-sample model is noisy: at 160x120 a 0.2 px noise moves its rotation by degrees)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def skew(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    def unpack(x):
        Rx = Rotation.from_rotvec(x[:3]).as_matrix() @ R
        tx = t + x[3:]
        return Rx, tx / np.linalg.norm(tx)

    def residuals(x):
        Rx, tx = unpack(x)
        return _sampson(skew(tx) @ Rx, xa, xb)

    res = least_squares(residuals, np.zeros(6), loss="soft_l1", f_scale=scale, max_nfev=200)
    return unpack(res.x)


def image_pose(src_view: Any, tgt_view: Any, m: Any, cfg: SiftDltConfig) -> dict[str, Any] | None:
    """Relative camera pose of two views from their 2D matches ``m`` (image points only), the scale of the
    translation from depth. Returns ``{"T": 4x4 cam_src -> cam_tgt, "inliers": (n,) bool, "n_scaled": int}``
    or None when the essential matrix or the scale cannot be estimated."""
    import cv2

    if len(m.uv_a) < max(5, cfg.min_inliers):
        return None
    ua, ub = np.asarray(m.uv_a, np.float64), np.asarray(m.uv_b, np.float64)
    xa, xb = _normalised(ua, src_view.intrinsics), _normalised(ub, tgt_view.intrinsics)
    f = 0.5 * (float(np.asarray(src_view.intrinsics)[0, 0]) + float(np.asarray(tgt_view.intrinsics)[0, 0]))
    E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.RANSAC, prob=cfg.confidence,
                                   threshold=cfg.threshold / f)
    if E is None or E.shape != (3, 3):  # none, or several solutions stacked: take none
        if E is None or E.shape[0] % 3 or E.shape[1] != 3:
            return None
        E = E[:3]
    out = cv2.recoverPose(E, xa, xb, np.eye(3), mask=mask.copy())
    R, t, pose_mask = out[1], out[2], out[3]
    inl = pose_mask.reshape(-1) > 0
    if inl.sum() < cfg.min_inliers:
        return None
    if cfg.refine:
        R, t = _refine_pose(R, t.reshape(3), xa[inl], xb[inl], cfg.threshold / f)
        t = t.reshape(3, 1)
    Xh = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), np.hstack([R, t.reshape(3, 1)]),
                               xa.T.astype(np.float64), xb.T.astype(np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (Xh[:3] / Xh[3:]).T  # triangulated points in the source camera, |t| = 1
    Xb = X @ R.T + t.reshape(1, 3)
    za = _depth_at(src_view, ua, cfg.depth_min, cfg.depth_max)
    zb = _depth_at(tgt_view, ub, cfg.depth_min, cfg.depth_max)
    ratios = []
    for z_depth, z_tri in ((za, X[:, 2]), (zb, Xb[:, 2])):
        ok = inl & np.isfinite(z_depth) & (z_tri > 1e-9)
        ratios.append(z_depth[ok] / z_tri[ok])
    r = np.concatenate(ratios)
    if len(r) < cfg.min_inliers:
        return None
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = float(np.median(r)) * t.reshape(3)
    return {"T": T, "inliers": inl, "n_scaled": int(len(r))}


def register_sift_dlt(
    src_views: Sequence[Any],
    tgt_views: Sequence[Any],
    cfg: BaselineConfig | None = None,
    seed: int = 0,
    matcher: Callable[[np.ndarray, np.ndarray], Any] | None = None,
) -> BaselineResult:
    """SIFT-DLT (the paper's): relative pose of a view pair from its image matches (essential matrix), the
    scale from depth, carried to the fragments by the views' poses; the view pair with the most inliers
    counts. The identity when no pair gives a pose. ``src_corr``/``tgt_corr``: the inlier matches of that
    pair lifted with depth (for the inlier ratio)."""
    import cv2

    cfg = cfg or BaselineConfig()
    c = cfg.sift_dlt
    if not src_views or not tgt_views:
        raise ValueError("sift_dlt needs the RGB-D views of both fragments (none were given)")
    cv2.setRNGSeed(int(seed))
    matcher = matcher or _default_matcher(c)
    best, n_matches = None, 0
    for a, b in _view_pairs(len(src_views), len(tgt_views), c.view_pairs):
        m = matcher(src_views[a].color, tgt_views[b].color)
        n_matches += len(m.uv_a)
        pose = image_pose(src_views[a], tgt_views[b], m, c)
        if pose is not None and (best is None or pose["inliers"].sum() > best[0]["inliers"].sum()):
            best = (pose, a, b, m)
    empty = np.zeros((0, 3))
    if best is None:
        return BaselineResult(np.eye(4), 0.0, float("nan"), empty, empty, {"n_correspondences": 0, "n_matches": n_matches})
    pose, a, b, m = best
    Pa, Pb = np.asarray(src_views[a].pose, np.float64), np.asarray(tgt_views[b].pose, np.float64)
    T = Pb @ pose["T"] @ np.linalg.inv(Pa)  # src fragment -> cam a -> cam b -> tgt fragment
    inl = pose["inliers"]
    ps, vs = lift_pixels(np.asarray(m.uv_a)[inl], src_views[a], c.depth_min, c.depth_max)
    pt, vt = lift_pixels(np.asarray(m.uv_b)[inl], tgt_views[b], c.depth_min, c.depth_max)
    ok = vs & vt
    n_inl = int(inl.sum())
    return BaselineResult(T, n_inl / max(len(inl), 1), float("nan"), ps[ok], pt[ok],
                          {"n_correspondences": int(ok.sum()), "n_matches": n_matches, "n_inliers": n_inl,
                           "view_pair": (a, b), "n_scaled": pose["n_scaled"]})


# --------------------------------------------------------------------------- dispatch


def register_pair(
    method: str,
    src_points: np.ndarray | None,
    tgt_points: np.ndarray | None,
    *,
    src_colors: np.ndarray | None = None,
    tgt_colors: np.ndarray | None = None,
    src_views: Sequence[Any] = (),
    tgt_views: Sequence[Any] = (),
    init: np.ndarray | None = None,
    cfg: BaselineConfig | None = None,
    seed: int = 0,
) -> BaselineResult:
    """Register one pair with a classical ``method`` (``fpfh | icp | color_icp | sift_dlt | sift_lifted``)."""
    cfg = cfg or BaselineConfig()
    if method == "fpfh":
        return register_fpfh(src_points, tgt_points, cfg, seed)
    if method == "icp":
        return register_icp(src_points, tgt_points, init, cfg.icp)
    if method == "color_icp":
        return register_color_icp(src_points, src_colors, tgt_points, tgt_colors, init, cfg.color_icp)
    if method == "sift_dlt":
        return register_sift_dlt(src_views, tgt_views, cfg, seed)
    if method == "sift_lifted":
        return register_sift_lifted(src_views, tgt_views, cfg, seed)
    raise ConfigError("method", method, " | ".join(METHODS))
