"""Settings that the run config writes under two names, and the check that both names agree.

``conf/run.yaml`` keeps a few settings where a researcher sweeps them (``views``, ``window_size``,
``eval.ransac_distance``, ...) and mirrors each, by interpolation, into the group whose code reads it
(``projection.views``, ``registration.ransac.distance``, ...). Each pair is *one* setting: the first
name (the primary) is the one to set, the mirror follows it. Setting only the mirror would change
what the code computes without changing the key that sweeps, run names and the report filter on
(or, the other way round, change the config hash without changing anything), so two names that
disagree are an error naming both (:func:`check_mirrors`).

Outside the run config (``python -m pcrcg.evaluate`` composes the ``registration`` group alone) a
pair may have only one of its names; nothing is checked then.
"""

from __future__ import annotations

from typing import Any, Mapping

from pcrcg.errors import ConfigError

# (primary, mirror): set the primary, the mirror follows it by interpolation
MIRRORS: tuple[tuple[str, str], ...] = (
    ("views", "projection.views"),
    ("window_size", "projection.window_size"),
    ("eval.n_points", "registration.n_points"),
    ("eval.ransac_iterations", "registration.ransac.max_iterations"),
    ("eval.ransac_distance", "registration.ransac.distance"),
)

_MISSING = object()


def lookup(data: Mapping[str, Any] | Any, dotted: str) -> Any:
    """The value at a dotted key of plain nested mappings (or attribute objects), or ``_MISSING``."""
    node: Any = data
    for part in dotted.split("."):
        if isinstance(node, Mapping):
            if part not in node:
                return _MISSING
            node = node[part]
        elif node is not None and hasattr(node, part):
            node = getattr(node, part)
        else:
            return _MISSING
    return node


def present(value: Any) -> bool:
    return value is not _MISSING and value is not None


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    return a == b


def check_mirrors(data: Mapping[str, Any]) -> None:
    """Raise :class:`~pcrcg.errors.ConfigError` naming both keys when a primary and its mirror differ.

    ``data``: the resolved config as plain containers.
    """
    for primary, mirror in MIRRORS:
        a, b = lookup(data, primary), lookup(data, mirror)
        if present(a) and present(b) and not _same(a, b):
            raise ConfigError(mirror, b, f"the value of {primary} ({a!r}): {mirror} and {primary} are one setting, "
                                         f"{mirror} follows {primary}; set {primary}={b!r} instead")
