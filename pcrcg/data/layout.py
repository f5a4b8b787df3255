"""The 3DMatch on-disk layout: paths, readers and writers.

Everything the project reads or writes about a data set goes through here::

    <root>/splits/{train,val,test}.txt                 scene names, one per line
    <root>/fragments/<scene>/cloud_bin_<i>.ply         points (m), fragment frame = camera of first frame
    <root>/fragments/<scene>/cloud_bin_<i>.info.txt    "<scene> <seq> <first_frame_id> <last_frame_id>"
    <root>/rgbd/<scene>/camera-intrinsics.txt          3x3
    <root>/rgbd/<scene>/camera-intrinsics-color.txt    3x3, optional: colour not registered to depth
    <root>/rgbd/<scene>/<seq>/frame-XXXXXX.{color.png|color.jpg,depth.png,pose.txt}
    <root>/benchmarks/{3DMatch,3DLoMatch}/<scene>/{gt.log,gt.info,gt_overlap.log}
    <root>/pairs/{train,val}.txt                       "scene i j overlap" + 4x4 (j into i), see write_pairs

Conventions
-----------
* ``gt.log`` entry ``i j n`` holds the 4x4 that maps fragment ``j`` into fragment ``i``'s frame.
  In a pair the *source* is ``j`` and the *target* is ``i``.
* Poses (``.pose.txt``) are camera-to-world.
* ``gt.info`` is the 6x6 information matrix, translation first (3DMatch convention).
* Color frames are ``.color.png`` (7-Scenes, generated data) or ``.color.jpg`` (SUN3D, some
  published 7-Scenes samples); a frame has one of the two.
* A fragment's ``.info.txt`` is ours (first line, then ``#`` comments) or the release's (first line,
  then the fragment's 4x4 pose); only the first line is read.
"""

from __future__ import annotations

import io
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from pcrcg.errors import DataError

BENCHMARKS = ("3DMatch", "3DLoMatch")
SPLITS = ("train", "val", "test")
# suffixes of a frame's color image, in order of preference when both exist
COLOR_SUFFIXES = (".color.png", ".color.jpg")


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class PairRecord:
    """One pair of fragments of a scene: ``transform`` (4x4) maps fragment j into fragment i."""

    scene: str
    i: int
    j: int
    transform: np.ndarray
    overlap: float = float("nan")
    n_fragments: int = 0


@dataclass(frozen=True)
class FragmentInfo:
    """The frames fused into one fragment (the first line of ``cloud_bin_<i>.info.txt``)."""

    scene: str
    seq: str
    first_frame: int
    last_frame: int

    def frame_ids(self) -> list[int]:
        return list(range(self.first_frame, self.last_frame + 1))


# --------------------------------------------------------------------------- paths


class Layout:
    """Paths of a data set in the 3DMatch layout rooted at ``root``."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def split_file(self, split: str) -> Path:
        return self.root / "splits" / f"{split}.txt"

    def pairs_file(self, split: str) -> Path:
        return self.root / "pairs" / f"{split}.txt"

    def fragments_dir(self, scene: str) -> Path:
        return self.root / "fragments" / scene

    def fragment(self, scene: str, i: int) -> Path:
        return self.fragments_dir(scene) / f"cloud_bin_{i}.ply"

    def fragment_info(self, scene: str, i: int) -> Path:
        return self.fragments_dir(scene) / f"cloud_bin_{i}.info.txt"

    def rgbd_dir(self, scene: str) -> Path:
        return self.root / "rgbd" / scene

    def intrinsics(self, scene: str) -> Path:
        return self.rgbd_dir(scene) / "camera-intrinsics.txt"

    def color_intrinsics(self, scene: str) -> Path:
        """Optional: the colour camera's own intrinsics, where colour is not registered to depth
        (7-Scenes); absent: colour and depth share ``camera-intrinsics.txt``."""
        return self.rgbd_dir(scene) / "camera-intrinsics-color.txt"

    def frame_prefix(self, scene: str, seq: str, frame: int) -> Path:
        return self.rgbd_dir(scene) / seq / f"frame-{frame:06d}"

    def benchmark_dir(self, benchmark: str, scene: str | None = None) -> Path:
        d = self.root / "benchmarks" / benchmark
        return d / scene if scene is not None else d

    def manifest(self) -> Path:
        return self.root / "manifest.json"

    def scenes(self, split: str) -> list[str]:
        return read_split(self.split_file(split))

    def n_fragments(self, scene: str) -> int:
        d = self.fragments_dir(scene)
        if not d.is_dir():
            raise DataError(d, "fragment folder of scene is missing")
        return len(list(d.glob("cloud_bin_*.ply")))


def color_path(prefix: Path) -> Path:
    """The color image of a frame given ``.../frame-XXXXXX``: ``.color.png`` or ``.color.jpg``,
    whichever exists (``.color.png`` when neither does, so that errors name the usual file)."""
    prefix = Path(prefix)
    for suffix in COLOR_SUFFIXES:
        p = prefix.with_name(prefix.name + suffix)
        if p.is_file():
            return p
    return prefix.with_name(prefix.name + COLOR_SUFFIXES[0])


def frame_paths(prefix: Path) -> tuple[Path, Path, Path]:
    """(color, depth, pose) paths of a frame given ``.../frame-XXXXXX``."""
    prefix = Path(prefix)
    return (
        color_path(prefix),
        prefix.with_name(prefix.name + ".depth.png"),
        prefix.with_name(prefix.name + ".pose.txt"),
    )


def frame_ids(frames_dir: str | os.PathLike) -> list[int]:
    """Sorted ids of the frames in a folder: every ``frame-XXXXXX.color.png`` or ``.color.jpg``
    (other files are not looked at; an absent folder has none)."""
    d = Path(frames_dir)
    ids: set[int] = set()
    for suffix in COLOR_SUFFIXES:
        for p in d.glob(f"frame-*{suffix}"):
            num = p.name[len("frame-"): -len(suffix)]
            if num.isdigit():
                ids.add(int(num))
    return sorted(ids)


# --------------------------------------------------------------------------- text files


def _need(path: Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file is missing")
    return path


def _entries(path: Path, size: int, what: str) -> list[tuple[int, list[list[str]]]]:
    """The non-empty lines of a log file in groups of ``size``: (the file's line number of the group's first line,
    its lines split into words). A file that does not split into such groups is a DataError naming it."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise DataError(path, f"not a text file (a {what} is text)") from None
    rows = [(n, ln.split()) for n, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    if len(rows) % size:
        raise DataError(path, f"{len(rows)} non-empty lines; a {what} holds groups of {size}")
    return [(rows[k][0], [r for _, r in rows[k : k + size]]) for k in range(0, len(rows), size)]


def _matrix(path: Path, line: int, rows: list[list[str]], n: int) -> np.ndarray:
    """The n x n matrix of an entry starting at the file's ``line`` (its header there, the rows after it)."""
    values = []
    for k, r in enumerate(rows):
        at = f"entry at line {line}: line {line + 1 + k}"
        if len(r) != n:
            raise DataError(path, f"{at} holds {len(r)} values, not {n}: {' '.join(r)[:80]!r}")
        try:
            values.append([float(v) for v in r])
        except ValueError:
            raise DataError(path, f"{at} is not {n} numbers: {' '.join(r)[:80]!r}") from None
    return np.array(values, dtype=np.float64)


def read_split(path: str | os.PathLike) -> list[str]:
    path = _need(Path(path))
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]


def write_split(path: str | os.PathLike, scenes: Iterable[str]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{s}\n" for s in scenes))


def read_matrix(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read a whitespace-separated matrix of ``shape``; NaN/inf or a wrong count is an error."""
    path = _need(Path(path))
    try:
        vals = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError as exc:
        raise DataError(path, f"not a numeric matrix ({exc})") from None
    if vals.size != shape[0] * shape[1]:
        raise DataError(path, f"expected {shape[0]}x{shape[1]} numbers, found {vals.size}")
    if not np.all(np.isfinite(vals)):
        raise DataError(path, "matrix holds NaN or inf")
    return vals.reshape(shape)


def check_rigid(T: np.ndarray, where: object, tol: float = 1e-3) -> np.ndarray:
    """Raise DataError unless ``T`` (4x4) is a finite rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DataError(where, f"transform must be 4x4, got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise DataError(where, "transform holds NaN or inf")
    R = T[:3, :3]
    if (
        np.abs(R @ R.T - np.eye(3)).max() > tol
        or abs(np.linalg.det(R) - 1.0) > tol
        or np.abs(T[3] - [0, 0, 0, 1]).max() > tol
    ):
        raise DataError(where, "transform is not rigid (rotation not orthonormal or last row not 0 0 0 1)")
    return T


def read_pose(path: str | os.PathLike) -> np.ndarray:
    """A 4x4 camera-to-world pose, checked to be rigid."""
    return check_rigid(read_matrix(path, (4, 4)), path)


def write_matrix(path: str | os.PathLike, M: np.ndarray) -> None:
    Path(path).write_text(format_matrix(M))


def format_matrix(M: np.ndarray) -> str:
    return "".join("\t".join(f"{v: .10e}" for v in row) + "\n" for row in np.asarray(M))


def read_intrinsics(path: str | os.PathLike) -> np.ndarray:
    K = read_matrix(path, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
        raise DataError(path, "not a pinhole intrinsics matrix (fx, fy > 0, last row 0 0 1)")
    return K


def pinhole(values: Any, setting: str) -> np.ndarray:
    """The 3x3 intrinsics of a config value ``[fx, fy, cx, cy]`` (pixels); a ConfigError naming
    ``setting`` for anything else."""
    from pcrcg.errors import ConfigError

    ok = (isinstance(values, (list, tuple)) and len(values) == 4
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in values))
    if not ok or float(values[0]) <= 0 or float(values[1]) <= 0:
        raise ConfigError(setting, values, "[fx, fy, cx, cy] in pixels with fx, fy > 0")
    fx, fy, cx, cy = (float(x) for x in values)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def color_camera(layout: "Layout", scene: str, K_depth: np.ndarray) -> np.ndarray | None:
    """The colour camera's intrinsics (3, 3) of a scene when they differ from the depth camera's
    ``K_depth``, else None."""
    path = layout.color_intrinsics(scene)
    if not path.is_file():
        return None
    K = read_intrinsics(path)
    return None if np.allclose(K, K_depth) else K


def color_to_depth_camera(color: np.ndarray, K_color: np.ndarray, K_depth: np.ndarray) -> np.ndarray:
    """A colour image (H, W, 3) taken with intrinsics ``K_color`` resampled (bilinear) into the
    depth camera's ``K_depth``, so that colour pixel (u, v) sees what depth pixel (u, v) sees. Both
    matrices are for the image's own size; the two cameras' small baseline is ignored (7-Scenes
    gives no extrinsics). Pixels outside the colour image are black."""
    import cv2

    H, W = color.shape[:2]
    A = np.asarray(K_color, np.float64) @ np.linalg.inv(np.asarray(K_depth, np.float64))  # depth px -> colour px
    return cv2.warpPerspective(np.ascontiguousarray(color), A, (W, H),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT)


def read_fragment_info(path: str | os.PathLike) -> FragmentInfo:
    path = _need(Path(path))
    parts = path.read_text().split("\n", 1)[0].split()
    if len(parts) < 4:
        raise DataError(path, "first line must be '<scene> <seq> <first_frame_id> <last_frame_id>'")
    try:
        first, last = int(parts[2]), int(parts[3])
    except ValueError:
        raise DataError(path, "frame ids on the first line are not integers") from None
    if last < first:
        raise DataError(path, f"last frame {last} precedes first frame {first}")
    return FragmentInfo(parts[0], parts[1], first, last)


def write_fragment_info(path: str | os.PathLike, info: FragmentInfo, extra: str = "") -> None:
    text = f"{info.scene} {info.seq} {info.first_frame} {info.last_frame}\n" + extra
    Path(path).write_text(text)


# --------------------------------------------------------------------------- gt files


def read_gt_log(path: str | os.PathLike, scene: str = "") -> list[PairRecord]:
    """Entries of a ``gt.log`` / ``est.log``: ``i j n`` then a 4x4 (j into i)."""
    path = _need(Path(path))
    out = []
    for line, rows in _entries(path, 5, "gt.log"):
        head = rows[0]
        try:
            i, j, n = int(head[0]), int(head[1]), int(head[2])
        except (ValueError, IndexError):
            raise DataError(path, f"malformed entry at line {line}: expected 'i j n' (three integers), got "
                                  f"{' '.join(head)[:80]!r}") from None
        T = _matrix(path, line, rows[1:], 4)
        if not np.all(np.isfinite(T)):
            raise DataError(path, f"entry at line {line}: transform holds NaN or inf")
        out.append(PairRecord(scene, i, j, T, n_fragments=n))
    return out


def write_gt_log(path: str | os.PathLike, pairs: Sequence[PairRecord]) -> None:
    buf = io.StringIO()
    for p in pairs:
        buf.write(f"{p.i}\t {p.j}\t {p.n_fragments}\t\n")
        buf.write(format_matrix(p.transform))
    atomic_write_text(Path(path), buf.getvalue())


def read_gt_info(path: str | os.PathLike) -> dict[tuple[int, int], np.ndarray]:
    """``gt.info``: ``i j n`` then a 6x6 information matrix per pair."""
    path = _need(Path(path))
    out = {}
    for line, rows in _entries(path, 7, "gt.info"):
        try:
            i, j = int(rows[0][0]), int(rows[0][1])
        except (ValueError, IndexError):
            raise DataError(path, f"malformed entry at line {line}: expected 'i j n' (integers), got "
                                  f"{' '.join(rows[0])[:80]!r}") from None
        out[(i, j)] = _matrix(path, line, rows[1:], 6)
    return out


def write_gt_info(
    path: str | os.PathLike, pairs: Sequence[PairRecord], infos: Sequence[np.ndarray]
) -> None:
    buf = io.StringIO()
    for p, M in zip(pairs, infos, strict=True):
        buf.write(f"{p.i}\t {p.j}\t {p.n_fragments}\t\n")
        buf.write(format_matrix(M))
    atomic_write_text(Path(path), buf.getvalue())


def read_gt_overlap(path: str | os.PathLike) -> dict[tuple[int, int], float]:
    """``gt_overlap.log``: lines ``i,j,overlap``."""
    path = _need(Path(path))
    out = {}
    for n, ln in enumerate(path.read_text().splitlines(), 1):
        if not ln.strip():
            continue
        parts = ln.replace(",", " ").split()
        try:
            out[(int(parts[0]), int(parts[1]))] = float(parts[2])
        except (ValueError, IndexError):
            raise DataError(path, f"line {n} is not 'i,j,overlap'") from None
    return out


def write_gt_overlap(path: str | os.PathLike, pairs: Sequence[PairRecord]) -> None:
    atomic_write_text(Path(path), "".join(f"{p.i},{p.j},{p.overlap:.4f}\n" for p in pairs))


def write_pairs(path: str | os.PathLike, pairs: Sequence[PairRecord]) -> None:
    """Training/validation pairs: ``scene i j overlap`` then the 4x4 (j into i)."""
    buf = io.StringIO()
    for p in pairs:
        buf.write(f"{p.scene} {p.i} {p.j} {p.overlap:.4f}\n")
        buf.write(format_matrix(p.transform))
    atomic_write_text(Path(path), buf.getvalue())


def read_pairs(path: str | os.PathLike) -> list[PairRecord]:
    path = _need(Path(path))
    out = []
    for line, rows in _entries(path, 5, "pairs file"):
        h = rows[0]
        try:
            scene, i, j, overlap = h[0], int(h[1]), int(h[2]), float(h[3])
        except (ValueError, IndexError):
            raise DataError(path, f"malformed entry at line {line}: expected 'scene i j overlap', got "
                                  f"{' '.join(h)[:80]!r}") from None
        out.append(PairRecord(scene, i, j, _matrix(path, line, rows[1:], 4), overlap))
    return out


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a ``.partial`` file and a rename: never a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- images


def read_color(path: str | os.PathLike) -> np.ndarray:
    """An RGB image as (H, W, 3) uint8. A missing or undecodable file is a DataError."""
    import cv2

    path = _need(Path(path))
    _check_image_complete(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(path, "cannot decode the color image (corrupt PNG/JPEG?)")
    return np.ascontiguousarray(img[:, :, ::-1])


def read_depth(path: str | os.PathLike, depth_scale: float = 1000.0) -> np.ndarray:
    """A depth PNG (uint16, mm, 0 = none) as (H, W) float32 metres (0 = none)."""
    import cv2

    path = _need(Path(path))
    _check_image_complete(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(path, "cannot decode the depth image (corrupt PNG?)")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise DataError(path, f"depth must be a single-channel uint16 PNG, got {img.dtype} {img.shape}")
    return img.astype(np.float32) / np.float32(depth_scale)


def _check_image_complete(path: Path) -> None:
    """OpenCV decodes truncated PNGs and JPEGs silently (rows of zeros or gray, a warning at most):
    a file that starts as a PNG must end with its IEND chunk, one that starts as a JPEG with its
    end-of-image marker FFD9 (zero padding after it is allowed). Other bytes are left to the decoder."""
    with open(path, "rb") as f:
        head = f.read(8)
        f.seek(max(0, path.stat().st_size - 64))
        tail = f.read()
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        if b"IEND" not in tail[-12:]:
            raise DataError(path, "PNG is truncated (no IEND chunk)")
    elif head.startswith(b"\xff\xd8\xff") and not tail.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise DataError(path, "JPEG is truncated (no end-of-image marker FFD9)")


def write_color(path: str | os.PathLike, rgb: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1])):
        raise DataError(path, "could not write image")


def write_depth(path: str | os.PathLike, depth_m: np.ndarray, depth_scale: float = 1000.0) -> None:
    import cv2

    mm = np.clip(np.round(depth_m * depth_scale), 0, 65535).astype(np.uint16)
    if not cv2.imwrite(str(path), mm):
        raise DataError(path, "could not write depth image")


# --------------------------------------------------------------------------- point clouds


def write_ply(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY: float32 xyz, optional uint8 rgb (colors in [0, 1] or uint8)."""
    pts = np.asarray(points, dtype="<f4")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}"]
    header += [f"property float {c}" for c in "xyz"]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        col = np.asarray(colors)
        if col.dtype != np.uint8:
            col = np.clip(np.round(col * 255.0), 0, 255).astype(np.uint8)
        header += [f"property uchar {c}" for c in ("red", "green", "blue")]
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    header.append("end_header")
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = col[:, 0], col[:, 1], col[:, 2]
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
    os.replace(tmp, path)


# PLY scalar types -> NumPy kinds (the names of the PLY spec and their sized aliases)
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Points (N, 3) float64 and colors (N, 3) float64 in [0, 1] (or None) of a PLY file whose first element
    is ``vertex`` with scalar properties (ascii or binary, either byte order): what :func:`write_ply`
    writes and most point clouds are, read by NumPy alone, the same values as Open3D's reader (uchar
    colors / 255, float colors as they are). None for a layout this reader leaves to Open3D (another first
    element, a list property in the vertices, colors of another type); a file that is not PLY, or holds
    fewer vertices than its header declares, is a :class:`DataError` naming it."""
    path = _need(Path(path))
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise DataError(path, "is not a PLY file (no 'ply' magic line)")
        fmt, elements, props = None, [], []
        while True:
            line = f.readline()
            if not line:
                raise DataError(path, "PLY header has no end_header line")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format" and len(words) >= 2:
                fmt = words[1]
            elif words[0] == "element" and len(words) == 3:
                if not words[2].isdigit():
                    raise DataError(path, f"PLY element {words[1]!r} has no count: {line.strip()[:80]!r}")
                elements.append((words[1], int(words[2])))
            elif words[0] == "property" and len(elements) == 1:
                props.append(words[1:])
        if fmt not in _PLY_FORMATS:
            raise DataError(path, f"PLY format {fmt!r} is not one of {sorted(_PLY_FORMATS)}")
        if not elements or elements[0][0] != "vertex" or any(len(p) != 2 or p[0] not in _PLY_TYPES for p in props):
            return None
        names = [p[1] for p in props]
        if not all(c in names for c in "xyz"):
            raise DataError(path, f"PLY vertices have no x, y, z (properties: {names})")
        n = elements[0][1]
        order = _PLY_FORMATS[fmt]
        kinds = {p[1]: _PLY_TYPES[p[0]] for p in props}
        if order is None:
            try:
                rows = np.loadtxt(f, dtype=np.float64, max_rows=n, ndmin=2) if n else np.zeros((0, len(props)))
            except ValueError as exc:
                raise DataError(path, f"PLY text is not numbers ({' '.join(str(exc).split())[:120]})") from None
            if rows.shape != (n, len(props)):
                raise DataError(path, f"PLY declares {n} vertices of {len(props)} values; the text holds {rows.shape}")
            cols = {name: rows[:, k] for k, name in enumerate(names)}
        else:
            dt = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in props])
            data = f.read(n * dt.itemsize)
            if len(data) < n * dt.itemsize:
                raise DataError(path, f"PLY is truncated: {n} vertices declared, {len(data) // dt.itemsize} present")
            rec = np.frombuffer(data, dtype=dt, count=n)
            cols = {name: rec[name] for name in names}
    pts = np.stack([cols[c].astype(np.float64) for c in "xyz"], axis=1)
    rgb = ("red", "green", "blue")
    if not all(c in cols for c in rgb):
        return pts, None
    kind = {kinds[c] for c in rgb}
    if kind == {"u1"}:
        return pts, np.stack([cols[c].astype(np.float64) / 255.0 for c in rgb], axis=1)
    if kind <= {"f4", "f8"}:
        return pts, np.stack([cols[c].astype(np.float64) for c in rgb], axis=1)
    return None


def read_cloud(path: str | os.PathLike, dtype: Any = np.float32) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) float32 (``dtype``: float64 keeps far-from-origin coordinates exact) and colors
    (N, 3) float32 in [0, 1] or None.

    Reads ``.ply`` (:func:`read_ply`, by NumPy; by Open3D the layouts it leaves), ``.pcd`` (Open3D), ``.npz``
    (keys ``points``/``pcd``/``xyz`` and optional ``colors``) and Predator's ``.pth`` arrays. A ``.pth`` is
    opened with ``torch.load(weights_only=True)`` and, failing that (numpy arrays, as in Predator's release:
    legacy non-zip ``torch.save`` files), by a reader that resolves numpy's array reconstruction
    only; no code from the file is ever executed.
    """
    path = _need(Path(path))
    suffix = path.suffix.lower()
    if suffix == ".ply":
        read = read_ply(path)
        if read is not None:
            pts, cols = read
            if len(pts) == 0:
                raise DataError(path, "point cloud is empty or unreadable")
            return _check_points(pts.astype(dtype), path), None if cols is None else cols.astype(np.float32)
    if suffix in (".ply", ".pcd"):
        import open3d as o3d

        pcd = o3d.io.read_point_cloud(str(path))
        pts = np.asarray(pcd.points, dtype=dtype)
        if len(pts) == 0:
            raise DataError(path, "point cloud is empty or unreadable")
        cols = np.asarray(pcd.colors, dtype=np.float32) if pcd.has_colors() else None
        return _check_points(pts, path), cols
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                key = next((k for k in ("points", "pcd", "xyz") if k in z), None)
                if key is None:
                    raise DataError(path, f"npz has no 'points' array (keys: {sorted(z.files)})")
                pts = np.asarray(z[key], dtype=dtype)
                cols = np.asarray(z["colors"], dtype=np.float32) if "colors" in z else None
        except DataError:
            raise
        except (ValueError, OSError, EOFError) as exc:  # pickled objects (refused), not a zip, truncated
            raise DataError(path, f"is not an npz of numeric arrays ({' '.join(str(exc).split())[:160]})") from None
        return _check_points(pts, path), cols
    if suffix == ".pth":
        return _check_points(np.asarray(_load_pth_points(path), dtype=dtype), path), None
    raise DataError(path, f"unsupported point cloud format {suffix!r} (use .ply, .pcd, .npz or .pth)")


def _check_points(pts: np.ndarray, path: Path) -> np.ndarray:
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise DataError(path, f"expected an (N, 3) array of points, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise DataError(path, "points hold NaN or inf")
    return pts


def _load_pth_points(path: Path) -> np.ndarray:
    """The (N, 3) array of a ``.pth`` file: a tensor/array (or a dict with ``points``/``pcd``/``xyz``).

    ``torch.load(weights_only=True)`` reads tensors; Predator's fragments are numpy arrays, which
    that loader refuses, so they are read by :func:`_restricted_pth_unpickle` (numpy's array
    reconstruction only).
    """
    import pickle

    import torch

    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, zipfile.BadZipFile, EOFError, ValueError, TypeError):
        try:
            obj = _restricted_pth_unpickle(path.read_bytes())
        except Exception as exc:  # noqa: BLE001 - reported with the file name, on one line
            msg = " ".join(str(exc).split()) or exc.__class__.__name__
            raise DataError(path, f"cannot read .pth safely: {msg}") from None
    if isinstance(obj, dict):
        obj = next((obj[k] for k in ("points", "pcd", "xyz") if k in obj), None)
        if obj is None:
            raise DataError(path, "dict in .pth has no 'points' entry")
    if hasattr(obj, "numpy"):
        obj = obj.numpy()
    try:
        return np.asarray(obj, dtype=np.float32)
    except (TypeError, ValueError):
        raise DataError(path, f".pth holds a {type(obj).__name__}, not an array of points") from None


# The only globals a .pth may name: numpy's array reconstruction and what its pickles use.
_ALLOWED_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("collections", "OrderedDict"),
    ("_codecs", "encode"),  # how pickle protocol 2 stores raw array bytes
}
# torch.save's legacy (non-zip) format: pickles of this number, the protocol version and a dict of
# system facts, then the object, then the list of tensor storage keys (and the storages' bytes)
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001


def _restricted_unpickler(buf: io.BytesIO, allow_globals: bool = True):
    """A pickle reader that resolves only ``_ALLOWED_GLOBALS`` (none when ``allow_globals`` is
    false) and refuses tensor storages (persistent ids): nothing in the file is ever executed."""
    import pickle

    class _Restricted(pickle.Unpickler):
        def find_class(self, module, name):
            if allow_globals and (module, name) in _ALLOWED_GLOBALS:
                return super().find_class(module, name)
            raise pickle.UnpicklingError(f"global {module}.{name} is not allowed (a .pth is read as numpy arrays only)")

        def persistent_load(self, pid):
            raise pickle.UnpicklingError("holds tensor storages that torch.load(weights_only=True) could not read")

    return _Restricted(buf)


def _restricted_pth_unpickle(raw: bytes):
    """The object of a ``torch.save`` file (zip or legacy) or of a plain pickle, numpy arrays only.

    Zip files: ``archive/data.pkl``. Legacy files: the magic number, protocol and system info are
    checked, then the object's pickle is read (the storage keys after it are not needed for arrays).
    """
    if raw[:2] == b"PK":  # torch zip container: the pickle is <archive>/data.pkl
        with zipfile.ZipFile(io.BytesIO(raw)) as zf:
            name = next((n for n in zf.namelist() if n.endswith("data.pkl")), None)
            if name is None:
                raise ValueError("zip archive without data.pkl")
            return _restricted_unpickler(io.BytesIO(zf.read(name))).load()
    buf = io.BytesIO(raw)
    first = _restricted_unpickler(buf).load()
    if not (isinstance(first, int) and first == _LEGACY_MAGIC):
        return first  # a plain pickle of the object
    protocol = _restricted_unpickler(buf, allow_globals=False).load()
    if protocol != _LEGACY_PROTOCOL:
        raise ValueError(f"legacy torch.save protocol {protocol!r}, expected {_LEGACY_PROTOCOL}")
    sys_info = _restricted_unpickler(buf, allow_globals=False).load()
    if not isinstance(sys_info, dict):
        raise ValueError("legacy torch.save file without its system-info record")
    if sys_info.get("little_endian") is False:
        raise ValueError("big-endian legacy torch.save files are not supported")
    return _restricted_unpickler(buf).load()


def evenly(items: list, n: int | None) -> list:
    """At most ``n`` items spread evenly over the list, in order (all for n None or 0): a subset of
    test pairs that samples every scene and every part of a trajectory, unlike the first n."""
    items = list(items)
    if not n or n >= len(items):
        return items
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, int(n))).astype(int))
    return [items[k] for k in idx]
