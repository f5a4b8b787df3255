"""pcrcg.safeload: torch files read without running code from them, every failure one line naming the file."""

from __future__ import annotations

import os
import pickle

import pytest
import torch

from pcrcg.errors import DataError
from pcrcg.safeload import load_tensors


class _Evil:
    """Unpickling this calls os.system: what a crafted weights file does."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_a_torch_file_of_tensors_and_plain_values_reads_back(tmp_path):
    path = tmp_path / "w.pth"
    torch.save({"a": torch.arange(3), "meta": {"k": [1, "x"]}}, path)
    got = load_tensors(path, "encoder2d.weights")
    assert torch.equal(got["a"], torch.arange(3)) and got["meta"] == {"k": [1, "x"]}


def test_a_crafted_pickle_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pth"
    torch.save({"state_dict": _Evil(str(marker))}, path)  # a torch file whose pickle calls os.system
    with pytest.raises(DataError) as info:
        load_tensors(path, "encoder2d.weights")
    msg = str(info.value)
    assert msg.startswith(f"{path}: encoder2d.weights: refused by torch.load(weights_only=True): it would call")
    assert "system" in msg and "\n" not in msg
    assert "weights_only` set to `False" not in msg and "weights_only set to False" not in msg  # never the unsafe advice
    assert not marker.exists()
    plain = tmp_path / "plain.pkl"  # a bare pickle of the same: refused too
    plain.write_bytes(pickle.dumps(_Evil(str(marker))))
    with pytest.raises(DataError, match="refused by torch.load"):
        load_tensors(plain)
    assert not marker.exists()


@pytest.mark.parametrize("content", [b"x", b"not a torch file at all\n" * 10])
def test_junk_is_one_line_naming_file_and_setting(tmp_path, content):
    path = tmp_path / "junk.pth"
    path.write_bytes(content)
    with pytest.raises(DataError) as info:
        load_tensors(path, "encoder2d.weights")
    msg = str(info.value)
    assert msg.startswith(f"{path}: encoder2d.weights: ") and "\n" not in msg


def test_a_truncated_file_is_corrupt_or_truncated(tmp_path):
    good = tmp_path / "good.pth"
    torch.save({"w": torch.zeros(1000)}, good)
    cut = tmp_path / "cut.pth"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DataError, match=r"cut\.pth: is not a readable torch file, corrupt or truncated\?"):
        load_tensors(cut)


def test_a_missing_file_says_so(tmp_path):
    with pytest.raises(DataError, match=r"nope\.pth: checkpoint: file does not exist"):
        load_tensors(tmp_path / "nope.pth", "checkpoint")
