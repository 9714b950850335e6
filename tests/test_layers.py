"""Layers point down: the core library never imports the bench (the simulator, the demo, the
command line) or LeRobot, the LeRobot integration imports only the core, and no modules of
the package import each other in a cycle. Read from the source (ast), nothing is imported."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "gensplat_transforms"
#: The bench: may import the core and gensplat_lerobot; nothing in the core imports it.
BENCH = (f"{PACKAGE}.sim", f"{PACKAGE}.demo", f"{PACKAGE}.cli")
INTEGRATION = "gensplat_lerobot"


def _name(path: Path, base: Path) -> str:
    parts = path.relative_to(base).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p, ROOT): p for p in sorted((ROOT / PACKAGE).rglob("*.py"))}
INTEGRATION_MODULES = {
    _name(p, ROOT / "integrations"): p for p in sorted((ROOT / "integrations").rglob("*.py"))
}


def _under(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _type_checking(node: ast.AST) -> bool:
    """``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``): its imports never run."""
    test = node.test if isinstance(node, ast.If) else None
    return isinstance(test, ast.Name) and test.id == "TYPE_CHECKING" or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _statements(tree: ast.Module, module_level: bool):
    """Import statements anywhere, or only those that run on import (not inside functions, nor
    under ``if TYPE_CHECKING:``)."""
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif module_level and _type_checking(node):
            todo.extend(node.orelse)
        elif not (module_level and isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))):
            todo.extend(ast.iter_child_nodes(node))


def imports(name: str, path: Path, modules: dict, module_level: bool = False) -> set[str]:
    """Absolute names of what ``name`` imports: ``from a import b`` gives ``a.b`` when that is
    a module of ``modules``, else ``a``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in _statements(ast.parse(path.read_text()), module_level):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
            continue
        base = node.module or ""
        if node.level:
            parts = package.split(".")[: len(package.split(".")) - node.level + 1]
            base = ".".join(parts + ([node.module] if node.module else []))
        out |= {f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names}
    return out


def test_the_core_imports_neither_the_bench_nor_lerobot():
    forbidden = (*BENCH, INTEGRATION, "lerobot")
    bad = {m: sorted(i for i in imports(m, p, MODULES) if _under(i, forbidden))
           for m, p in MODULES.items() if not _under(m, BENCH)}  # fmt: skip
    assert not {m: i for m, i in bad.items() if i}, "core modules import the bench or LeRobot"


def test_the_model_does_not_import_the_reconstructors():
    """``geometry/model/`` (the network) sits below the reconstructors of ``geometry/`` (which
    wrap it): the types both use (views, reconstructions) live in ``core/views.py``, below both."""
    model = f"{PACKAGE}.geometry.model"
    bad = {m: sorted(i for i in imports(m, p, MODULES) if _under(i, (f"{PACKAGE}.geometry",)) and not _under(i, (model,)))
           for m, p in MODULES.items() if _under(m, (model,))}  # fmt: skip
    assert not {m: i for m, i in bad.items() if i}, "geometry/model/ imports the reconstructors"


def test_the_lerobot_integration_imports_only_the_core():
    bad = {m: sorted(i for i in imports(m, p, INTEGRATION_MODULES) if _under(i, BENCH))
           for m, p in INTEGRATION_MODULES.items()}  # fmt: skip
    assert not {m: i for m, i in bad.items() if i}


def _graph() -> dict[str, set[str]]:
    """Module-level imports between the package's modules; importing ``a.b.c`` from outside
    ``a.b`` also runs ``a.b``'s ``__init__``."""
    graph = {}
    for m, p in MODULES.items():
        edges = set()
        for target in imports(m, p, MODULES, module_level=True):
            parts = target.split(".")
            for k in range(1, len(parts) + 1):
                parent = ".".join(parts[:k])
                if parent in MODULES and parent != m and not _under(m, [parent]):
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
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_batch_path_shares_the_workers_helpers_instead_of_reaching_into_the_transform():
    """batched.py takes the config, the plan's keys and the view helpers from the modules that
    hold them; from transform.py only the transform's type (for annotations)."""
    tree = ast.parse(MODULES[f"{PACKAGE}.render.batched"].read_text())
    from_transform = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "transform"
                      for a in n.names}  # fmt: skip
    assert from_transform == {"GenSplatTransform"}
    assert imports(f"{PACKAGE}.render.batched", MODULES[f"{PACKAGE}.render.batched"], MODULES) >= {
        f"{PACKAGE}.views.plan", f"{PACKAGE}.settings", f"{PACKAGE}.render.output", f"{PACKAGE}.views.perturbation"}


def test_no_module_name_is_used_twice_within_a_stage():
    """A module's folder names its stage (``data/format.py``, ``cache/format.py``): within one
    stage (its subpackages included) or one integration no two modules share a file name
    (``__init__.py`` aside), and no module shares its name with a package beside it (the
    package would win)."""
    paths = [p for base in (ROOT / PACKAGE, ROOT / "integrations") for p in base.rglob("*.py") if p.name != "__init__.py"]
    stages = {}
    for p in paths:
        top = p.relative_to(ROOT / PACKAGE if p.is_relative_to(ROOT / PACKAGE) else ROOT / "integrations").parts
        stages.setdefault(top[0] if len(top) > 1 else PACKAGE, []).append(p)
    repeated = {s: sorted({p.name for p in ps if [q.name for q in ps].count(p.name) > 1}) for s, ps in stages.items()}
    assert not {s: n for s, n in repeated.items() if n}
    assert not [p for p in paths if (p.parent / p.stem / "__init__.py").exists()]
