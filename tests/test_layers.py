"""Layers point down. The package is folders by pipeline stage, lowest first: ``core`` <
``data`` < ``calibration`` < ``geometry`` < ``cache`` < ``views`` < ``render`` < the top
modules (``settings``, ``transform``, ``training``, the package's ``__init__``); above it the
integrations ``gensplat_lerobot`` < ``gensplat_sim`` < ``gensplat_cli``. A module imports only
its own stage and lower ones, at module or function level alike; the package never imports
LeRobot or an integration; no modules import each other in a cycle, function-level imports
counted. Imports under ``if TYPE_CHECKING:`` never run: they are no edges of the cycle check,
and may name the top's settings and transform types (what the stages are handed) from any
stage. Read from the source (ast), nothing is imported."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "gensplat_transforms"
#: the package's stage folders, lowest first (docs/architecture.md)
STAGES = ("core", "data", "calibration", "geometry", "cache", "views", "rendering")
#: the package's modules above every stage (and the package's ``__init__``)
TOP = (f"{PACKAGE}.settings", f"{PACKAGE}.transform", f"{PACKAGE}.training")
#: the shipped network's weights: package data beside the stages, read by the geometry stage
WEIGHTS = f"{PACKAGE}.weights"
#: the integrations, lowest first; each may import the package and the ones before it
INTEGRATIONS = ("gensplat_lerobot", "gensplat_sim", "gensplat_cli")
#: what a stage may name in a type-only import from above it: the objects it is handed
TYPES_FROM_ABOVE = (f"{PACKAGE}.settings", f"{PACKAGE}.transform")


def _name(path: Path, base: Path) -> str:
    parts = path.relative_to(base).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p, ROOT): p for p in sorted((ROOT / PACKAGE).rglob("*.py"))}
INTEGRATION_MODULES = {
    _name(p, ROOT / "integrations"): p for p in sorted((ROOT / "integrations").rglob("*.py"))
}
ALL_MODULES = {**MODULES, **INTEGRATION_MODULES}


def _under(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def rank(name: str) -> int | None:
    """The layer of a module or package of the project, lowest 0; None for other modules."""
    top = len(STAGES)
    if _under(name, [WEIGHTS]):
        return STAGES.index("geometry")
    if name == PACKAGE or _under(name, TOP):
        return top
    for i, stage in enumerate(STAGES):
        if _under(name, [f"{PACKAGE}.{stage}"]):
            return i
    for i, integration in enumerate(INTEGRATIONS):
        if _under(name, [integration]):
            return top + 1 + i
    return None


def _type_checking(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``): its imports never run."""
    test = node.test if isinstance(node, ast.If) else None
    return isinstance(test, ast.Name) and test.id == "TYPE_CHECKING" or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _statements(tree: ast.Module, module_level: bool, types: bool = False):
    """Import statements that run (functions included), only those that run on import (not
    inside functions) with ``module_level``, or with ``types`` those under ``if TYPE_CHECKING:``
    (which never run)."""
    todo = [(node, False, False) for node in tree.body]  # (node, in a function, type-only)
    while todo:
        node, in_function, type_only = todo.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            if type_only == types and not (module_level and in_function):
                yield node
            continue
        in_function = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        if _type_checking(node):
            todo += [(n, in_function, True) for n in node.body]
            todo += [(n, in_function, type_only) for n in node.orelse]
        else:
            todo += [(n, in_function, type_only) for n in ast.iter_child_nodes(node)]


def imports(name: str, path: Path, modules: dict, module_level: bool = False,
            types: bool = False) -> set[str]:
    """Absolute names of what ``name`` imports (see :func:`_statements` for which statements):
    ``from a import b`` gives ``a.b`` when that is a module of ``modules``, else ``a``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in _statements(ast.parse(path.read_text()), module_level, types):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
            continue
        base = node.module or ""
        if node.level:
            parts = package.split(".")[: len(package.split(".")) - node.level + 1]
            base = ".".join(parts + ([node.module] if node.module else []))
        out |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names}
    return out


def test_every_module_belongs_to_a_layer():
    assert not [m for m in ALL_MODULES if rank(m) is None]
    assert all((ROOT / PACKAGE / stage / "__init__.py").is_file() for stage in STAGES)
    assert [rank(f"{PACKAGE}.{s}.x") for s in STAGES] == list(range(len(STAGES)))
    order = [f"{PACKAGE}.rendering.batched", f"{PACKAGE}.transform", "gensplat_lerobot.plugin",
             "gensplat_sim.demo", "gensplat_cli"]
    assert [rank(m) for m in order] == sorted({rank(m) for m in order})


def test_modules_import_only_their_own_layer_and_lower_ones():
    """At module or function level alike: a function-level import is an arrow too."""
    up = {m: sorted(i for i in imports(m, p, ALL_MODULES) if (rank(i) or 0) > rank(m))
          for m, p in ALL_MODULES.items()}  # fmt: skip
    assert not {m: i for m, i in up.items() if i}, "imports that point up"


def test_type_only_imports_name_only_the_types_the_stages_are_handed_from_above():
    up = {m: sorted(i for i in imports(m, p, ALL_MODULES, types=True)
                    if (rank(i) or 0) > rank(m) and not _under(i, TYPES_FROM_ABOVE))
          for m, p in ALL_MODULES.items()}  # fmt: skip
    assert not {m: i for m, i in up.items() if i}


def test_the_package_imports_neither_lerobot_nor_an_integration():
    forbidden = (*INTEGRATIONS, "lerobot")
    every = {m: imports(m, p, MODULES) | imports(m, p, MODULES, types=True) for m, p in MODULES.items()}
    bad = {m: sorted(i for i in names if _under(i, forbidden)) for m, names in every.items()}
    assert not {m: i for m, i in bad.items() if i}, "the package imports LeRobot or an integration"


def test_the_model_does_not_import_the_reconstructors():
    """``geometry/model/`` (the network) sits below the reconstructors of ``geometry/`` (which
    wrap it): the types both use (views, reconstructions) live in ``core/views.py``, below both."""
    model = f"{PACKAGE}.geometry.model"
    inside = {m: imports(m, p, MODULES) for m, p in MODULES.items() if _under(m, [model])}
    bad = {m: sorted(i for i in names if _under(i, [f"{PACKAGE}.geometry"]) and not _under(i, [model]))
           for m, names in inside.items()}  # fmt: skip
    assert not {m: i for m, i in bad.items() if i}, "geometry/model/ imports the reconstructors"


def _graph(module_level: bool = False) -> dict[str, set[str]]:
    """Imports between the project's modules (the package and the integrations), function-level
    ones too unless ``module_level``; importing ``a.b.c`` from outside ``a.b`` also runs
    ``a.b``'s ``__init__`` (a module's own packages are running already; importing one of them
    by name, ``from . import x``, is an edge)."""
    graph = {}
    for m, p in ALL_MODULES.items():
        edges = set()
        for target in imports(m, p, ALL_MODULES, module_level=module_level):
            parts = target.split(".")
            for k in range(1, len(parts) + 1):
                parent = ".".join(parts[:k])
                if parent in ALL_MODULES and parent != m and (parent == target or not _under(m, [parent])):
                    edges.add(parent)
        graph[m] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state, path = {}, []

    def visit(u):
        state[u] = "open"
        path.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == "open":
                return path[path.index(v) :] + [v]
            if v not in state and (cycle := visit(v)):
                return cycle
        path.pop()
        state[u] = "done"
        return None

    return next((c for u in sorted(graph) if u not in state and (c := visit(u))), None)


def test_no_import_cycles():
    graph = _graph()
    assert f"{PACKAGE}.geometry.model" in graph[f"{PACKAGE}.geometry.feedforward"]  # the graph sees imports
    assert "gensplat_sim.demo" in graph["gensplat_cli.commands"]  # ... function-level ones too
    assert "gensplat_sim.demo" not in _graph(module_level=True)["gensplat_cli.commands"]
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_checks_see_function_level_and_type_only_imports():
    tree = ast.parse("import a\nif TYPE_CHECKING:\n    import t\ndef f():\n    import b\n")
    names = lambda **kw: {a.name for n in _statements(tree, **kw) for a in n.names}
    assert names(module_level=False) == {"a", "b"}
    assert names(module_level=True) == {"a"}
    assert names(module_level=False, types=True) == {"t"}


def test_the_batch_path_reads_and_renders_through_the_workers_interfaces():
    """rendering/batched.py reaches no stage's internals: it reads the cache through the
    transform's reader (``cache.reader``), takes the plan's keys from ``views.plan`` and renders
    with the worker's own function (``rendering.output``); the config and the transform only as
    types (for annotations), from transform.py only the transform's type."""
    name = f"{PACKAGE}.rendering.batched"
    tree = ast.parse(MODULES[name].read_text())
    from_transform = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "transform"
                      for a in n.names}  # fmt: skip
    assert from_transform == {"GenSplatTransform"}
    package = {m for m in imports(name, MODULES[name], MODULES) if m.startswith(PACKAGE)}
    assert package == {f"{PACKAGE}.cache.reader", f"{PACKAGE}.views.plan", f"{PACKAGE}.rendering",
                       f"{PACKAGE}.rendering.output", f"{PACKAGE}.core.views"}  # fmt: skip
    assert imports(name, MODULES[name], MODULES, types=True) <= set(TYPES_FROM_ABOVE)


def test_no_module_name_is_used_twice_within_a_stage():
    """A module's folder names its stage (``data/format.py``, ``cache/format.py``): within one
    stage (its subpackages included) or one integration no two modules share a file name
    (``__init__.py`` aside), and no module shares its name with a package beside it (the
    package would win)."""
    paths = [p for base in (ROOT / PACKAGE, ROOT / "integrations") for p in base.rglob("*.py") if p.name != "__init__.py"]
    stages = {}
    for p in paths:
        base = ROOT / PACKAGE if p.is_relative_to(ROOT / PACKAGE) else ROOT / "integrations"
        parts = p.relative_to(base).parts
        stages.setdefault(parts[0] if len(parts) > 1 else PACKAGE, []).append(p)
    repeated = {s: sorted({p.name for p in ps if [q.name for q in ps].count(p.name) > 1})
                for s, ps in stages.items()}  # fmt: skip
    assert not {s: n for s, n in repeated.items() if n}
    assert not [p for p in paths if (p.parent / p.stem / "__init__.py").exists()]
