"""The package's shape: no import cycles, and every import points down the layers.

Imports are read from the source (every `import` / `from ... import`, at module
level or inside functions), so a lazy import cannot hide a cycle.
"""
import ast
from pathlib import Path

import multirace

PACKAGE = Path(multirace.__file__).parent
# lowest first; a module may import its own layer and the layers below it
LAYERS = ["resources", "text", "atomic", "options", "sim", "sensors", "environment", "recording", "racing", "deepracer", "league", "train", "tools", "cli"]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> set[str]:
    """The multirace modules that the file at `path` imports."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("multirace")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("multirace"):
                continue
            for alias in node.names:  # `from .x import y` may name a submodule y
                sub = f"{target}.{alias.name}"
                found.add(sub if MODULES.get(sub) else target)
    return {m for m in found if m in MODULES and m != name}


MODULES = {module_name(p): p for p in PACKAGE.rglob("*.py")}
GRAPH = {name: imports_of(path) for name, path in MODULES.items()}


def layer(name: str) -> str:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_no_import_cycles():
    state, stack, cycles = {}, [], []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(GRAPH[node]):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(GRAPH):
        if node not in state:
            visit(node)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_imports_point_down_the_layers():
    rank = {name: i for i, name in enumerate(LAYERS)}
    rank["text"] = rank["atomic"] = rank["options"] = rank["resources"]  # the package base
    rank["league"] = rank["train"]
    wrong = []
    for name, targets in GRAPH.items():
        here = layer(name)
        if here not in rank:  # the package's own __init__ (the public API) sits on top
            continue
        for target in targets:
            there = layer(target)
            if there not in rank or rank[there] > rank[here] or (rank[there] == rank[here] and there != here):
                wrong.append(f"{name} -> {target}")
    assert not wrong, "imports that point up (or across) the layers: " + ", ".join(sorted(wrong))
    assert set(LAYERS) - {"resources", "text", "atomic", "options", "cli"} == {p.name for p in PACKAGE.iterdir()
                                                  if (p / "__init__.py").exists()}, "a layer folder is missing"
