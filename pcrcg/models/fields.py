"""Settings dataclasses built from config nodes: one helper for "the node's keys that are my fields"."""

from __future__ import annotations

from typing import Any, Mapping


def known_fields(cls: type, m: Mapping[str, Any] | None, **overrides: Any) -> dict[str, Any]:
    """The entries of ``m`` (a config node; None: empty) that are fields of dataclass ``cls`` (other
    keys, e.g. another model's, are ignored), with ``overrides`` on top."""
    names = set(cls.__dataclass_fields__)
    return {**{k: v for k, v in dict(m or {}).items() if k in names}, **overrides}
