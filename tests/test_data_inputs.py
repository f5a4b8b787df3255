"""pcrcg.data.inputs: the stamp of a passed input check is kept per set of files (a sweep's learned and
classical runs read different sets), survives reaching the data set through a link, and goes stale when a
checked file changes; a bad file is still named."""

import json
import os
import shutil

import pytest

from pcrcg.data import inputs
from pcrcg.data.inputs import STAMP, STAMP_KEEP, check_inputs
from pcrcg.data.layout import Layout
from pcrcg.errors import DataError

LEARNED = (["train", "val"], ["3DMatch", "3DLoMatch"])  # what a run that trains reads
CLASSICAL = ([], ["3DMatch", "3DLoMatch"])  # FPFH, ICP: the test scenes only


def _check(root, which) -> int:
    """1 when the stamp answered, 0 when the files were read."""
    return check_inputs(Layout(root), *which, log=lambda m: None, workers=2)["cached"]


@pytest.fixture()
def root(tiny_root, tmp_path):
    dst = tmp_path / "data"
    shutil.copytree(tiny_root, dst)
    (dst / STAMP).unlink(missing_ok=True)
    return dst


def test_learned_and_classical_runs_keep_each_others_stamps(root):
    assert _check(root, LEARNED) == 0 and _check(root, LEARNED) == 1
    assert _check(root, CLASSICAL) == 0  # another set of files: read once
    assert _check(root, LEARNED) == 1 and _check(root, CLASSICAL) == 1  # both stamps kept
    held = json.loads((root / STAMP).read_text())["signatures"]
    assert len(held) == 2


def test_the_stamp_holds_through_a_link_and_after_a_move(root, tmp_path):
    assert _check(root, LEARNED) == 0
    link = tmp_path / "link"
    os.symlink(root, link)
    assert _check(link, LEARNED) == 1
    moved = tmp_path / "moved"
    os.replace(root, moved)
    assert _check(moved, LEARNED) == 1


def test_a_changed_file_is_read_again_and_a_bad_one_named(root):
    assert _check(root, CLASSICAL) == 0
    layout = Layout(root)
    scene = layout.scenes("test")[0]
    png = sorted((layout.rgbd_dir(scene) / "seq-01").glob("*.color.png"))[2]
    data = png.read_bytes()
    png.write_bytes(data)
    os.utime(png, ns=(png.stat().st_atime_ns, png.stat().st_mtime_ns + 10**9))  # same bytes, newer time
    assert _check(root, CLASSICAL) == 0
    png.write_bytes(data[:200])
    with pytest.raises(DataError, match=png.name):
        _check(root, CLASSICAL)
    with pytest.raises(DataError, match=png.name):  # the stamp a learned run left before does not hide it
        _check(root, LEARNED)


@pytest.mark.parametrize("old", ['{"signature": "%s"}', "not json", '{"signatures": ["a list"]}', ""])
def test_an_old_or_unreadable_stamp_means_one_check_again(root, old):
    (root / STAMP).write_text(old.replace("%s", "0" * 64))
    assert _check(root, CLASSICAL) == 0 and _check(root, CLASSICAL) == 1


def test_the_stamp_keeps_the_newest_signatures(tmp_path):
    stamp = tmp_path / STAMP
    for k in range(STAMP_KEEP + 4):
        inputs._write_stamp(stamp, f"key{k}")
    inputs._write_stamp(stamp, "key5")  # passed again: it becomes the newest and is not dropped next
    inputs._write_stamp(stamp, "new")
    held = list(json.loads(stamp.read_text())["signatures"])
    assert len(held) == STAMP_KEEP and held[-2:] == ["key5", "new"] and held[0] == "key6"  # key4 dropped
    assert not list(tmp_path.glob("*.tmp-*"))  # written whole, then renamed
