"""What every entry point does with bad input and interruptions: one line on stderr, no traceback.

* a :class:`~pcrcg.errors.PcrcgError` (a bad setting or file, named in its message): exit 2;
* Ctrl-C (``KeyboardInterrupt``): ``<prog>: interrupted (Ctrl-C)``, exit 130;
* SIGTERM (:class:`~pcrcg.errors.Terminated`, raised by :func:`sigterm_as_interrupt`'s handler):
  ``<prog>: terminated (SIGTERM)``, exit 143.

Used by ``pcrcg.run``, ``pcrcg.prepare``, ``pcrcg.evaluate``, ``pcrcg.report`` and ``pcrcg.pretrain2d``.
:func:`check_command_line` composes a command's config once before Hydra does, so that an override Hydra
cannot apply (an option or key that does not exist, a broken value) is also one line with exit 2.
"""

from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from pcrcg.errors import ConfigError, PcrcgError, Terminated, one_line


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


# Hydra's flags that take a value (skipped with it when the overrides are read from argv)
_VALUE_FLAGS = ("--config-path", "-cp", "--config-dir", "-cd", "--config-name", "-cn", "--experimental-rerun")
# flags after which Hydra composes nothing we should check first (help, printing the config, sweeps)
_LEFT_TO_HYDRA = ("--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c", "-m", "--multirun")


def command_line_overrides(argv: Sequence[str]) -> list[str]:
    """The ``key=value`` overrides among Hydra's command-line arguments ``argv`` (no program name)."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg in _VALUE_FLAGS:
            skip = True
            continue
        if arg.startswith("-") or "=" not in arg:
            continue
        out.append(arg)
    return out


def command_line_config_dirs(argv: Sequence[str]) -> list[Path]:
    """Config folders of a command line: ``conf/``, replaced by ``--config-path/-cp`` and extended by
    ``--config-dir/-cd``."""
    from pcrcg.config import CONF_DIR

    dirs = [CONF_DIR]
    for i, arg in enumerate(argv):
        for flag in ("--config-path", "-cp", "--config-dir", "-cd"):
            value = None
            if arg == flag and i + 1 < len(argv):
                value = argv[i + 1]
            elif arg.startswith(flag + "="):
                value = arg.split("=", 1)[1]
            if value is not None:
                p = Path(value).resolve()
                dirs = [p] if flag in ("--config-path", "-cp") else [*dirs, p]
    return dirs


def check_grammar(overrides: Sequence[str]) -> None:
    """Every override is in Hydra's override grammar; the first that is not raises a :class:`ConfigError`
    naming its key (Hydra's own message names no key)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    parser = OverridesParser.create()
    for override in overrides:
        try:
            parser.parse_overrides([override])
        except OverrideParseException as e:
            key, _, value = override.partition("=")
            raise ConfigError(key, value, "a value in Hydra's override grammar (quote one with brackets or commas: "
                                          f"key='...'): {str(e).splitlines()[0]}") from None


def check_command_line(config_name: str, argv: Sequence[str]) -> None:
    """Compose the config ``config_name`` (``conf/<config_name>.yaml``) with the overrides of ``argv`` once,
    before Hydra does: an override Hydra cannot apply (``data=nope``, ``nosuch=1``, ``x=[1,2``) raises a
    :class:`PcrcgError` (one line, exit 2 under :func:`one_line_errors`) instead of Hydra's multi-line report
    with exit 1. Help, ``--cfg``, sweeps, several config folders and another primary config are left to Hydra;
    ``hydra.*`` overrides are not composed here."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    dirs = command_line_config_dirs(argv)
    if any(a in _LEFT_TO_HYDRA for a in argv) or len(dirs) != 1 \
            or any(a.startswith(("--config-name", "-cn")) for a in argv):
        return
    overrides = [o for o in command_line_overrides(argv) if not o.startswith("hydra.")]
    check_grammar(overrides)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(dirs[0]), version_base="1.3"):
            compose(config_name=config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as e:
        lines = [ln.strip() for ln in str(e).splitlines()
                 if ln.strip() and not ln.strip().startswith(("full_key", "object_type", "provider=", "Config search"))]
        raise PcrcgError(f"cannot compose the config: {'; '.join(lines[:6])}") from None
    finally:
        GlobalHydra.instance().clear()


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
