"""Reading torch files without running code from them: the one home of ``torch.load(weights_only=True)``
for files a user names (checkpoints, 2D weights, the weights a package ships).

``weights_only=True`` reads tensors, plain containers and primitives only; a pickle that would call
anything else when loaded is refused. Every failure becomes one :class:`pcrcg.errors.DataError` line
naming the file (and the setting that named it), never torch's own multi-line advice, part of which
("re-running torch.load with weights_only set to False will likely succeed") is the unsafe way out.
"""

from __future__ import annotations

import pickle
import re
import warnings
from pathlib import Path
from typing import Any

from pcrcg.errors import DataError, one_line


def refusal_reason(e: BaseException) -> str:
    """The useful part of torch's weights-only refusal: what the pickle would call (``os.system``), or why
    the file is not a torch file at all."""
    text = str(e)
    m = re.search(r"GLOBAL (\S+)", text)
    if m:
        return f"it would call {m.group(1)} when loaded (a crafted or foreign pickle)"
    m = re.search(r"WeightsUnpickler error:\s*(.+)", text)
    if m:
        return f"not a torch checkpoint ({m.group(1).strip()[:120]})"
    return f"not a torch checkpoint ({one_line(e, 120)})"


def load_tensors(path: str | Path, setting: str | None = None) -> Any:
    """What the torch file at ``path`` holds, read on the CPU with ``torch.load(weights_only=True)``.

    A file that does not exist, is refused (it would run code) or cannot be read (truncated, corrupt, not a
    torch file) is a DataError: ``<path>: [<setting>: ]<why>``, one line.
    """
    import torch

    path = Path(path)
    lead = f"{setting}: " if setting else ""
    if not path.is_file():
        raise DataError(path, f"{lead}file does not exist")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Detected pickle protocol 4" and the like: the error says it all
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise DataError(path, f"{lead}refused by torch.load(weights_only=True): {refusal_reason(e)}; "
                              "only tensors and plain values are read, no code runs") from None
    except Exception as e:  # noqa: BLE001 - zip, storage and legacy-format errors: a file that is not a torch file
        raise DataError(path, f"{lead}is not a readable torch file, corrupt or truncated? "
                              f"({type(e).__name__}: {one_line(e, 160)})") from None
