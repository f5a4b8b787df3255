"""The layout's readers and writers, the official benchmark files, and bad input."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from conftest import shared_path
from pcrcg.data.layout import (
    PairRecord,
    read_cloud,
    read_color,
    read_depth,
    read_fragment_info,
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
    read_pose,
    write_color,
    write_depth,
    write_gt_info,
    write_gt_log,
    write_gt_overlap,
    write_matrix,
    write_ply,
)
from pcrcg.errors import DataError
from pcrcg.geometry import make_transform, random_rotation


def _pairs(n=3, seed=0):
    rng = np.random.default_rng(seed)
    return [PairRecord("s", k, k + 2, make_transform(random_rotation(rng), rng.normal(size=3)), 0.1 * (k + 1), 9)
            for k in range(n)]


@pytest.mark.parametrize("edit, message", [
    (lambda ls: ls.__setitem__(8, "0 1 garbage 0"), r"gt\.log: entry at line 8: line 9 is not 4 numbers: '0 1 garbage 0'"),
    (lambda ls: ls.__setitem__(9, "1 0 0"), r"gt\.log: entry at line 8: line 10 holds 3 values, not 4: '1 0 0'"),
    (lambda ls: ls.__setitem__(7, "1 x 9"), r"gt\.log: malformed entry at line 8: expected 'i j n' \(three integers\)"),
    (lambda ls: ls.pop(), r"gt\.log: 14 non-empty lines; a gt\.log holds groups of 5"),
])
def test_a_malformed_gt_log_names_the_files_own_line(tmp_path, edit, message):
    """Errors give the line of the file (blank lines counted), what is wrong and the text found there."""
    write_gt_log(tmp_path / "gt.log", _pairs())
    lines = (tmp_path / "gt.log").read_text().splitlines()
    lines.insert(5, "")  # two blank lines between the first two entries: the second starts at the file's line 8
    lines.insert(5, "")
    edit(lines)
    (tmp_path / "gt.log").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=message):
        read_gt_log(tmp_path / "gt.log")


def test_gt_files_round_trip(tmp_path):
    pairs = _pairs()
    infos = [np.arange(36, dtype=float).reshape(6, 6) + k for k in range(3)]
    write_gt_log(tmp_path / "gt.log", pairs)
    write_gt_info(tmp_path / "gt.info", pairs, infos)
    write_gt_overlap(tmp_path / "gt_overlap.log", pairs)
    back = read_gt_log(tmp_path / "gt.log", "s")
    assert [(p.i, p.j, p.n_fragments) for p in back] == [(0, 2, 9), (1, 3, 9), (2, 4, 9)]
    for a, b in zip(pairs, back):
        np.testing.assert_allclose(a.transform, b.transform, atol=1e-9)
    info = read_gt_info(tmp_path / "gt.info")
    np.testing.assert_allclose(info[(1, 3)], infos[1])
    assert read_gt_overlap(tmp_path / "gt_overlap.log") == {(0, 2): 0.1, (1, 3): 0.2, (2, 4): 0.3}


def test_official_benchmark_files_parse():
    root = shared_path("data", "3dmatch-benchmarks")
    counts = {}
    for bench in ("3DMatch", "3DLoMatch"):
        n = n_nonadj = 0
        for scene_dir in sorted((root / bench).iterdir()):
            recs = read_gt_log(scene_dir / "gt.log", scene_dir.name)
            info = read_gt_info(scene_dir / "gt.info")
            ov = read_gt_overlap(scene_dir / "gt_overlap.log")
            assert set(info) == {(r.i, r.j) for r in recs}
            # the official gt_overlap.log lists every pair i < j of the scene, not only the benchmark's
            assert set(ov) >= {(r.i, r.j) for r in recs}
            n_frag = recs[0].n_fragments
            assert len(ov) == n_frag * (n_frag - 1) // 2
            for r in recs:
                R = r.transform[:3, :3]
                assert np.abs(R @ R.T - np.eye(3)).max() < 1e-3  # the files are printed to ~1e-4
            n += len(recs)
            n_nonadj += sum(r.j != r.i + 1 for r in recs)
        counts[bench] = (n, n_nonadj)
    assert counts == {"3DMatch": (1623, 1279), "3DLoMatch": (1781, 1726)}


def test_official_overlaps_match_benchmark_split():
    root = shared_path("data", "3dmatch-benchmarks")
    def bench_overlaps(bench):
        out = []
        for d in (root / bench).iterdir():
            ov = read_gt_overlap(d / "gt_overlap.log")
            out += [ov[(r.i, r.j)] for r in read_gt_log(d / "gt.log")]
        return out

    lo, hi = bench_overlaps("3DLoMatch"), bench_overlaps("3DMatch")
    assert 0.1 <= min(lo) and max(lo) <= 0.3
    # the 3DMatch set predates the 3DLoMatch split: 100 of its 1623 pairs overlap less than 30%
    assert len(hi) == 1623 and sum(v <= 0.3 for v in hi) == 100 and min(hi) > 0.1


def test_pose_errors_name_the_file(tmp_path):
    p = tmp_path / "frame-000000.pose.txt"
    T = np.eye(4)
    T[0, 0] = np.nan
    write_matrix(p, T)
    with pytest.raises(DataError, match="frame-000000.pose.txt.*NaN"):
        read_pose(p)
    T = np.eye(4)
    T[0, 0] = 2.0
    write_matrix(p, T)
    with pytest.raises(DataError, match="not rigid"):
        read_pose(p)
    p.write_text("1 0 0\n0 1 0\n")
    with pytest.raises(DataError, match="expected 4x4"):
        read_pose(p)
    with pytest.raises(DataError, match="missing"):
        read_pose(tmp_path / "nope.pose.txt")


def test_images_round_trip_and_corruption(tmp_path):
    rng = np.random.default_rng(0)
    color = rng.integers(0, 255, size=(12, 16, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 3.0, size=(12, 16)).astype(np.float32)
    write_color(tmp_path / "c.png", color)
    write_depth(tmp_path / "d.png", depth)
    np.testing.assert_array_equal(read_color(tmp_path / "c.png"), color)
    np.testing.assert_allclose(read_depth(tmp_path / "d.png"), depth, atol=0.0005 + 1e-6)
    raw = (tmp_path / "c.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match="trunc.png"):
        read_color(tmp_path / "trunc.png")
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(DataError, match="junk.png.*decode"):
        read_depth(tmp_path / "junk.png")
    with pytest.raises(DataError, match="uint16"):
        read_depth(tmp_path / "c.png")


def test_fragment_info(tmp_path):
    p = tmp_path / "cloud_bin_0.info.txt"
    p.write_text("kitchen seq-01 100 149\nanything else\n")
    info = read_fragment_info(p)
    assert (info.scene, info.seq, info.first_frame, info.last_frame) == ("kitchen", "seq-01", 100, 149)
    p.write_text("kitchen seq-01\n")
    with pytest.raises(DataError, match="cloud_bin_0.info.txt"):
        read_fragment_info(p)


def test_clouds_ply_npz_pth(tmp_path):
    import torch

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.uniform(size=(100, 3)).astype(np.float32)
    write_ply(tmp_path / "a.ply", pts, cols)
    p2, c2 = read_cloud(tmp_path / "a.ply")
    np.testing.assert_allclose(p2, pts, atol=1e-6)
    np.testing.assert_allclose(c2, cols, atol=1 / 255)
    np.savez(tmp_path / "a.npz", points=pts)
    np.testing.assert_array_equal(read_cloud(tmp_path / "a.npz")[0], pts)
    torch.save(pts, tmp_path / "numpy.pth")  # Predator stores numpy arrays with torch.save
    np.testing.assert_array_equal(read_cloud(tmp_path / "numpy.pth")[0], pts)
    torch.save(torch.from_numpy(pts), tmp_path / "tensor.pth")
    np.testing.assert_array_equal(read_cloud(tmp_path / "tensor.pth")[0], pts)


def _ply(path, fmt, props, rows, extra_header=()):
    """A PLY file of the given format (ascii / binary_little_endian / binary_big_endian), vertex properties
    [(type, name)], rows (N, len(props)), and header lines before the vertex element."""
    kinds = {"float": "f4", "double": "f8", "uchar": "u1", "int": "i4", "ushort": "u2"}
    head = ["ply", f"format {fmt} 1.0", "comment made by the test", *extra_header, f"element vertex {len(rows)}"]
    head += [f"property {t} {n}" for t, n in props] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(head) + "\n").encode())
        if fmt == "ascii":
            f.write("".join(" ".join(repr(float(v)) if t in ("float", "double") else str(int(v))
                                     for (t, _), v in zip(props, r)) + "\n" for r in rows).encode())
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            rec = np.zeros(len(rows), dtype=[(n, order + kinds[t]) for t, n in props])
            for k, (_, n) in enumerate(props):
                rec[n] = [r[k] for r in rows]
            f.write(rec.tobytes())


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_read_by_numpy_as_open3d_reads_it(tmp_path, fmt):
    """read_ply (NumPy; what a run reads fragments with, so that a machine without Open3D runs) gives Open3D's
    values to the bit: points as doubles, uchar colors / 255, in every format and with other properties."""
    o3d = pytest.importorskip("open3d")
    from pcrcg.data.layout import read_ply

    rng = np.random.default_rng(3)
    n = 300
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    rgb = np.concatenate([np.arange(256), rng.integers(0, 256, n - 256)])[:, None].repeat(3, 1)
    rgb[:, 1] = rgb[::-1, 0]
    props = [("float", "x"), ("float", "y"), ("float", "z"), ("float", "nx"), ("uchar", "red"), ("uchar", "green"),
             ("uchar", "blue"), ("int", "label")]
    rows = [(*xyz[i], 0.5, *rgb[i], i) for i in range(n)]
    _ply(tmp_path / "c.ply", fmt, props, rows)
    pts, cols = read_ply(tmp_path / "c.ply")
    ref = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    assert np.array_equal(pts, np.asarray(ref.points)) and np.array_equal(cols, np.asarray(ref.colors))
    assert pts.dtype == np.float64 and cols.min() == 0.0 and cols.max() == 1.0
    # doubles, no colors; and what read_cloud gives (float32, as from Open3D's doubles)
    _ply(tmp_path / "d.ply", fmt, [("double", "x"), ("double", "y"), ("double", "z")], xyz.astype(np.float64) / 3)
    pts, cols = read_ply(tmp_path / "d.ply")
    ref = o3d.io.read_point_cloud(str(tmp_path / "d.ply"))
    assert cols is None and np.array_equal(pts, np.asarray(ref.points))
    p32, c32 = read_cloud(tmp_path / "d.ply")
    assert c32 is None and np.array_equal(p32, np.asarray(ref.points, dtype=np.float32))


def test_ply_reader_errors_and_what_it_leaves_to_open3d(tmp_path):
    from pcrcg.data.layout import read_ply

    props = [("float", "x"), ("float", "y"), ("float", "z")]
    _ply(tmp_path / "t.ply", "binary_little_endian", props, [(0, 0, 0)] * 10)
    data = (tmp_path / "t.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[:-7])  # the last vertex cut short
    with pytest.raises(DataError, match=r"t\.ply: PLY is truncated: 10 vertices declared, 9 present"):
        read_ply(tmp_path / "t.ply")
    (tmp_path / "n.ply").write_bytes(b"solid mesh\n")
    with pytest.raises(DataError, match=r"n\.ply: is not a PLY file"):
        read_cloud(tmp_path / "n.ply")
    _ply(tmp_path / "f.ply", "binary_little_endian", props, [(0, 0, 0)] * 3)
    text = (tmp_path / "f.ply").read_bytes()
    (tmp_path / "f.ply").write_bytes(text.replace(b"binary_little_endian", b"binary_middle"))
    with pytest.raises(DataError, match="PLY format 'binary_middle'"):
        read_ply(tmp_path / "f.ply")
    (tmp_path / "g.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                    "property float z\nend_header\n0 0 0\n1 two 3\n")
    with pytest.raises(DataError, match=r"g\.ply: PLY text is not numbers"):
        read_ply(tmp_path / "g.ply")
    (tmp_path / "e.ply").write_text("ply\nformat ascii 1.0\nelement vertex many\nend_header\n")
    with pytest.raises(DataError, match=r"e\.ply: PLY element 'vertex' has no count"):
        read_ply(tmp_path / "e.ply")
    _ply(tmp_path / "q.ply", "ascii", [("float", "a"), ("float", "b"), ("float", "c")], [(0, 0, 0)])
    with pytest.raises(DataError, match="no x, y, z"):
        read_ply(tmp_path / "q.ply")
    # another element first, or colors as ushort: Open3D's to read (read_ply says so with None)
    _ply(tmp_path / "m.ply", "ascii", props, [(1, 2, 3)], extra_header=["element face 0", "property list uchar int v"])
    assert read_ply(tmp_path / "m.ply") is None
    _ply(tmp_path / "u.ply", "ascii", [*props, ("ushort", "red"), ("ushort", "green"), ("ushort", "blue")],
         [(1, 2, 3, 9, 9, 9)])
    assert read_ply(tmp_path / "u.ply") is None


class _Evil:
    def __reduce__(self):
        return (open, ("/tmp/pcrcg-pwned", "w"))


def test_pth_never_executes_code(tmp_path):
    import os

    target = "/tmp/pcrcg-pwned"
    if os.path.exists(target):
        os.remove(target)
    with open(tmp_path / "evil.pth", "wb") as f:
        pickle.dump(_Evil(), f)
    with pytest.raises(DataError, match="evil.pth"):
        read_cloud(tmp_path / "evil.pth")
    assert not os.path.exists(target)


def test_cloud_shape_errors(tmp_path):
    np.savez(tmp_path / "bad.npz", points=np.zeros((5, 2)))
    with pytest.raises(DataError, match=r"bad.npz.*\(N, 3\)"):
        read_cloud(tmp_path / "bad.npz")
    with pytest.raises(DataError, match="unsupported"):
        (tmp_path / "x.xyz").write_text("1 2 3")
        read_cloud(tmp_path / "x.xyz")


def test_evenly_spreads_a_subset_over_the_whole_list():
    from pcrcg.data.layout import evenly

    items = [("a", k) for k in range(6)] + [("b", k) for k in range(6)]
    sub = evenly(items, 4)
    assert len(sub) == 4 and sub[0] == ("a", 0) and sub[-1] == ("b", 5)
    assert {s for s, _ in sub} == {"a", "b"}  # the first 4 would be scene a only
    assert evenly(items, None) == items and evenly(items, 0) == items and evenly(items, 50) == items
