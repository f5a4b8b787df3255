"""What every entry point does with bad input and interruptions: one line on stderr, no traceback.

* a :class:`~pcrcg.errors.PcrcgError` (a bad setting or file, named in its message): exit 2;
* Ctrl-C (``KeyboardInterrupt``): ``<prog>: interrupted (Ctrl-C)``, exit 130;
* SIGTERM (:class:`~pcrcg.errors.Terminated`, raised by :func:`sigterm_as_interrupt`'s handler):
  ``<prog>: terminated (SIGTERM)``, exit 143.

Used by ``pcrcg.run``, ``pcrcg.prepare``, ``pcrcg.evaluate``, ``pcrcg.report`` and ``pcrcg.pretrain2d``.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Any, Iterator, Mapping

from pcrcg.errors import PcrcgError, Terminated, one_line


def _raise_terminated(signum, frame) -> None:  # noqa: ANN001 - signal handler signature
    raise Terminated("SIGTERM")


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` (a ``KeyboardInterrupt``) inside the block, so that cleanup
    that runs on Ctrl-C also runs when a scheduler or ``kill`` ends the process. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interrupt_reason(exc: BaseException) -> str:
    return "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted (Ctrl-C)"


@contextmanager
def one_line_errors(prog: str) -> Iterator[None]:
    """Bad input (exit 2) and interruptions (exit 130 / 143) end the command with one line."""
    try:
        with sigterm_as_interrupt():
            yield
    except PcrcgError as exc:
        print(f"{prog}: error: {one_line(exc)}", file=sys.stderr, flush=True)
        sys.exit(2)
    except KeyboardInterrupt as exc:
        print(f"{prog}: {interrupt_reason(exc)}", file=sys.stderr, flush=True)
        sys.exit(143 if isinstance(exc, Terminated) else 130)


def json_safe(value: Any) -> Any:
    """``value`` with NaN/inf as None (JSON's null), numpy scalars and arrays, paths and tuples made
    plain: what :func:`strict_json` writes."""
    import math
    from pathlib import PurePath

    import numpy as np

    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, PurePath):
        return str(value)
    return str(value)


def strict_json(value: Any, **kw: Any) -> str:
    """JSON text with no bare ``NaN``/``Infinity`` (they are not JSON): null instead."""
    import json

    return json.dumps(json_safe(value), allow_nan=False, **kw)
