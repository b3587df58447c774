"""The package's import graph: no cycles, and layers that only import downwards.

Every `import` in every module counts, at module level or inside a function, and a
package's `__init__` is a module like any other: `from cogs.body import x` is an edge to
`cogs.body`, `from cogs.body import smpl_body` one to `cogs.body.smpl_body`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import cogs

ROOT = Path(cogs.__file__).parent


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _resolve(module: str, level: int, name: str | None, here: str, is_package: bool) -> str:
    if level == 0:
        return module
    base = here.split(".") if is_package else here.split(".")[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node.module or "", node.level, None, mod, is_pkg)
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    targets.append(sub if sub in mods else base)
            for t in targets:
                # `import cogs.a.b` names the module cogs.a.b (its parents' __init__s run,
                # but are not what the importer depends on).
                while t not in mods and "." in t:
                    t = t.rsplit(".", 1)[0]
                if t in mods and t != mod and t.startswith("cogs"):
                    graph[mod].add(t)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_function_level_and_package_imports():
    g = import_graph()
    assert "cogs.branches.human" in g["cogs.branches"]  # a package __init__ importing its modules
    assert "cogs.train.posefit" in g["cogs.train.trainer"]  # an import inside a function
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    cycles = _cycles(import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


# Layers, lowest first; a module may import its own layer and the ones before it.
LAYERS = [
    ("cogs", "cogs.errors", "cogs.log", "cogs.geometry", "cogs.ssim"),
    ("cogs.render",),
    ("cogs.body", "cogs.data"),
    ("cogs.branches",),
    ("cogs.model", "cogs.config"),
    ("cogs.train",),
    ("cogs.eval", "cogs.preprocess", "cogs.doctor", "cogs.use"),
    ("cogs.commands", "cogs.cli", "cogs.batch"),
]


def _layer(mod: str) -> int:
    best, rank = -1, None
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (mod == p or mod.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    assert rank is not None, f"{mod} belongs to no layer: add it to LAYERS"
    return rank


def test_imports_only_go_down_the_layers():
    """data -> branches -> model -> train, with eval and the commands on top; the renderer
    imports nothing of the method."""
    bad = [f"{m} (layer {_layer(m)}) imports {t} (layer {_layer(t)})"
           for m, targets in import_graph().items() for t in targets if _layer(t) > _layer(m)]
    assert not bad, "\n".join(sorted(bad))
