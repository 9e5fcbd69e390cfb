"""The parts of ``dagr_lite`` import downwards only (docs/design.md, "Layers"): no import goes up
the layer order, none lies on a cycle between parts, and no private name crosses a part."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "dagr_lite"
# Bottom to top: a part may import the parts before it, never one after it.
LAYERS = ("errors", "progress", "graph", "data", "synth", "nn", "eval", "config", "engine", "stream", "camera", "apps")


def part_of(module: str) -> str | None:
    """``dagr_lite.data.reader`` -> ``data``; ``dagr_lite.config`` -> ``config``; ``dagr_lite`` -> None."""
    bits = module.split(".")
    return bits[1] if len(bits) > 1 and bits[0] == "dagr_lite" else None


def imports_between_parts(package: Path = PACKAGE) -> list[tuple[str, str, str, list[str]]]:
    """``(where, from part, to part, names)`` for every import (at any depth of a module) from
    one part of the package to another."""
    found = []
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package.parent).with_suffix("")
        source = part_of(".".join(relative.parts))
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [(node.module, [a.name for a in node.names])]
                if node.module == "dagr_lite":  # from dagr_lite import data
                    targets = [(f"dagr_lite.{a.name}", []) for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [(a.name, []) for a in node.names]
            else:
                continue
            for module, names in targets:
                target = part_of(module)
                if target is not None and source is not None and target != source:
                    found.append((f"{relative}.py:{node.lineno}", source, target, names))
    return found


def problems(found: list[tuple[str, str, str, list[str]]], layers: tuple[str, ...] = LAYERS) -> list[str]:
    out = []
    edges: dict[str, set[str]] = {}
    for where, source, target, names in found:
        edges.setdefault(source, set()).add(target)
        for part in (source, target):
            if part not in layers:
                out.append(f"{where}: part {part!r} is in no layer; place it in LAYERS and docs/design.md")
        if source in layers and target in layers and layers.index(target) > layers.index(source):
            out.append(f"{where}: {source} imports {target}, a layer above it")
        out += [f"{where}: {source} imports {target}'s private name {n}" for n in names if n.startswith("_")]
    # Cycles between parts (the order above already forbids them; this says which parts they tie).
    for start in edges:
        stack, seen = [(start, [start])], set()
        while stack:
            node, trail = stack.pop()
            for nxt in edges.get(node, ()):
                if nxt == start:
                    out.append(f"parts on a cycle: {' -> '.join(trail + [start])}")
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, trail + [nxt]))
    return sorted(set(out))


def test_the_package_imports_downwards_only():
    found = imports_between_parts()
    assert len(found) > 50  # the parse sees the package's imports
    assert problems(found) == []


def test_the_check_finds_an_upward_import_a_cycle_and_a_private_name():
    found = [("a.py:1", "data", "engine", ["train"]), ("b.py:2", "engine", "data", ["_reader"]),
             ("c.py:3", "novel", "graph", [])]
    assert problems(found) == [
        "a.py:1: data imports engine, a layer above it",
        "b.py:2: engine imports data's private name _reader",
        "c.py:3: part 'novel' is in no layer; place it in LAYERS and docs/design.md",
        "parts on a cycle: data -> engine -> data",
        "parts on a cycle: engine -> data -> engine",
    ]
