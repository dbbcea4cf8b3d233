"""YAML that a person, a download or an attacker may have written: bounded before it is built.

PyYAML's aliases let a few hundred bytes stand for a billion nodes (the "billion laughs"): the
loaded object shares its parts, but anything that walks it (validation, an error message that
prints the value, a deep copy) expands it and exhausts memory. Configuration files and
``dataset.yaml`` never need that, so the node graph is measured after composing and before
constructing: more than :data:`MAX_NODES` nodes once aliases are expanded, or an alias that
contains itself, is refused. Files are also read only up to :data:`MAX_BYTES`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

__all__ = ["MAX_BYTES", "MAX_NODES", "UnsafeYaml", "load_bounded", "read_bounded"]

MAX_BYTES = 1 << 20  # a configuration or dataset.yaml is a few kB
MAX_NODES = 100_000  # scalars, lists and mappings, counting every alias as the copy it stands for


class UnsafeYaml(ValueError):
    """A YAML document refused before it was built (its message says why)."""


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def expanded_size(root: yaml.Node, limit: int = MAX_NODES) -> int:
    """Nodes in ``root`` with every alias expanded; UnsafeYaml past ``limit`` or on a recursive alias.

    Shared nodes are sized once (memoised), so this costs the composed graph's size, not the expansion's.
    """
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()  # ancestors of the node being sized: meeting one again is a cycle
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, children_done = stack.pop()
        key = id(node)
        if children_done:
            open_nodes.discard(key)
            sizes[key] = size = 1 + sum(sizes[id(c)] for c in _children(node))
            if size > limit:
                raise UnsafeYaml(f"its aliases expand to more than {limit} values (an alias bomb?); write the values out")
            continue
        if key in sizes:
            continue
        if key in open_nodes:
            raise UnsafeYaml("an alias refers to the node that contains it (a recursive document)")
        open_nodes.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node) if id(c) not in sizes)
    return sizes[id(root)]


class BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a document whose aliases expand past :data:`MAX_NODES`."""

    def compose_document(self) -> yaml.Node:
        node = super().compose_document()
        if node is not None:
            expanded_size(node)
        return node


def load_bounded(text: str) -> Any:
    """``yaml.safe_load`` with the alias bound. Raises UnsafeYaml, yaml.YAMLError, or RecursionError
    (PyYAML recurses per nesting level, so '[[[[…' a thousand deep)."""
    loader = BoundedLoader(text)
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def read_bounded(path: Path, limit: int = MAX_BYTES) -> str:
    """The UTF-8 text of a small file; UnsafeYaml if it is larger than ``limit`` bytes (read no further)."""
    with open(path, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:
        raise UnsafeYaml(f"larger than {limit // 1024} kB: not a file this program reads as YAML")
    return data.decode("utf-8")
