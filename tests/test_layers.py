"""The import graph: no cycles, no layer imports one above it (docs/layers.md).

Every ``import`` and ``from ... import`` of the package's sources is read with :mod:`ast`
(including imports inside functions: a lazy import is still a dependency), resolved to a
``blockray.*`` module, and checked against the layers:

    blockray (shared base)  <  rtl  <  synth, sim  <  host_driver  <  __main__

and inside host_driver, its subpackages in the order of the render's flow:

    scene, radiosity, board  <  traverse  <  cluster  <  render  <  cli (host_driver/cli.py)

A module may import its own package and the packages of lower layers only; synth and sim, on the
same layer, may not import each other. Module-level cycles are refused everywhere.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: source folder -> package (pyproject's package-dir)
FOLDERS = {"blockray": "blockray", "rtl": "blockray.rtl", "sim": "blockray.sim",
           "host_driver": "blockray.host_driver", "synth": "blockray.synth"}
#: package (or top module) -> layer; a module's layer is that of its longest listed prefix
LAYERS = {"blockray": 0, "blockray.rtl": 1, "blockray.synth": 2, "blockray.sim": 2,
          "blockray.host_driver": 3,
          # the scene, the form factors and solvers, the board driver with its transports: side by side
          "blockray.host_driver.scene": 3, "blockray.host_driver.radiosity": 3,
          "blockray.host_driver.board": 3,
          "blockray.host_driver.traverse": 4,     # voxel grid, block rays, visibility (form factors' weights)
          "blockray.host_driver.cluster": 5,      # --sets over Dask: boards, traversal, solvers
          "blockray.host_driver.render": 6,       # the render paths, their options and outputs, sweep
          "blockray.host_driver.cli": 7,
          "blockray.__main__": 8}     # python -m blockray: the entry point above the CLI
#: known violations, each with the issue that removes it (the test fails once it is gone, so the
#: entry is deleted with the fix)
KNOWN = {}
#: known module cycles, likewise
KNOWN_CYCLES = {}


def modules():
    """{module name: path} of every source file (subpackages: folders with an ``__init__.py``)."""
    out = {}
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).parts
            if not all((ROOT / folder).joinpath(*parts[:i], "__init__.py").exists() for i in range(len(parts))):
                continue                                     # a script beside data, not a module
            name = ".".join([package, *parts[:-1]] + ([] if path.stem == "__init__" else [path.stem]))
            out[name] = path
    return out


def imports(name, path, known):
    """The blockray modules ``name`` imports (resolved; ``from pkg import mod`` counts as mod)."""
    package = name if path.stem == "__init__" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module
            targets = [f"{stem}.{a.name}" if f"{stem}.{a.name}" in known else stem for a in node.names]
        else:
            continue
        found |= {t for t in targets if t in known and t != name}
    return found


def layer(module):
    """(package, rank) of the longest LAYERS prefix of ``module``."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n]), LAYERS[".".join(parts[:n])]
    raise KeyError(module)


def graph():
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def test_no_upward_or_sideways_imports():
    bad, used = [], set()
    for module, targets in graph().items():
        pkg, rank = layer(module)
        for target in sorted(targets):
            tpkg, trank = layer(target)
            if tpkg != pkg and trank >= rank:
                if (module, target) in KNOWN:
                    used.add((module, target))
                    continue
                bad.append(f"{module} (layer {rank}) imports {target} (layer {trank})")
    assert not bad, "\n".join(bad)
    assert used == set(KNOWN), f"fixed, delete from KNOWN: {set(KNOWN) - used}"


def test_no_import_cycles():
    g = graph()
    # Tarjan's strongly connected components
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in g[v]:
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
                cycles.append(sorted(comp))

    for v in g:
        if v not in index:
            visit(v)
    found = {tuple(c) for c in cycles}
    assert not found - set(KNOWN_CYCLES), f"import cycles: {sorted(found - set(KNOWN_CYCLES))}"
    assert found == set(KNOWN_CYCLES), f"fixed, delete from KNOWN_CYCLES: {set(KNOWN_CYCLES) - found}"


def test_the_checker_sees_imports():
    """The graph is not vacuous: known edges of each kind are found."""
    g = graph()
    assert "blockray.protocol" in g["blockray.rtl.board"]                 # relative, two dots
    assert "blockray.rtl.core" in g["blockray.sim.rtl_harness"]           # inside a function
    assert "blockray.host_driver.render.render" in g["blockray.host_driver.cli"]
    assert "blockray.sim.model" in g["blockray.host_driver.board.backends"]
