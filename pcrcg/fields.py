"""Reading config nodes: settings dataclasses built from a node ("the node's keys that are my fields")
and the accessors for one setting of a node (one key; a dotted path). No imports of the package, so
any module may use it."""

from __future__ import annotations

from typing import Any, Mapping, TypeVar

S = TypeVar("S", bound="NodeSettings")


def known_fields(cls: type, m: Mapping[str, Any] | None, **overrides: Any) -> dict[str, Any]:
    """The entries of ``m`` (a config node; None: empty) that are fields of dataclass ``cls`` (other
    keys, e.g. another model's, are ignored), with ``overrides`` on top."""
    names = set(cls.__dataclass_fields__)
    return {**{k: v for k, v in dict(m or {}).items() if k in names}, **overrides}


class NodeSettings:
    """Base of a settings dataclass made from its config node alone (a loss, the augmentation):
    ``from_mapping(node)`` takes the node's keys that are its fields."""

    @classmethod
    def from_mapping(cls: type[S], m: Mapping[str, Any] | None) -> S:
        return cls(**known_fields(cls, m))


def option(node: Any, key: str, default: Any = None) -> Any:
    """One key of a config node that is a mapping (``node.get``) or an object (an attribute);
    ``default`` when the node is None or has no such key."""
    if node is None:
        return default
    if isinstance(node, Mapping):
        return node.get(key, default)
    return getattr(node, key, default)


def lookup(node: Any, dotted: str, default: Any = None) -> Any:
    """The value at a dotted path (``"train.optimizer"``) of nested mappings; ``default`` where a
    part is missing or the node on the way is not a mapping."""
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node
