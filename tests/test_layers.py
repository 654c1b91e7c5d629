"""One-way layers: no import cycle inside torchcal/, and no import from a lower layer into a higher one.

The imports are read from the source (``ast``), module-level, inside functions and under ``if TYPE_CHECKING:``
alike: a type-only import is a dependency of the code's meaning, and a cycle hidden there is still a cycle.
A module's layer is that of its subpackage, or of the
module itself at the top level.
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchcal"

#: the layers, lowest first; a module may import from its own layer and the ones before it
LAYERS: list[set[str]] = [
    {"robot"},
    {"data", "effects"},
    {"estimate", "sim"},
    {"filter", "diagnose"},
    {"pipeline"},
    {"use"},
    {"report", "fleet", "sweep"},
    {"cli", "_entry", "__main__"},
]
#: leaf utilities: importable from anywhere, importing no other torchcal module but each other
LEAVES = {
    "_method",
    "errors",
    "_console",
    "_threads",
    "_version",
    "_outdir",
    "_inputs",
    "_device",
    "stats",
    "_dual",
    "_lbfgs",
    "_bounds",
    "_torch",
}
#: the package's __init__ re-exports from the layers (and reaches the pipeline lazily); nothing imports it
TOP = "__init__"


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def unit(module: str) -> str:
    """The first name below ``torchcal`` (``torchcal.estimate.lm`` -> ``estimate``; ``torchcal`` -> ``__init__``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else TOP


def imports(path: Path, modules: set[str]) -> set[str]:
    """torchcal modules ``path`` imports (a ``from package import name`` of a submodule counts as that module)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out: set[str] = set()

    def visit(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                out.update(a.name for a in child.names if a.name.split(".")[0] == "torchcal")
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    base = ".".join(
                        package.split(".")[: len(package.split(".")) - child.level + 1] + ([base] if base else [])
                    )
                if base.split(".")[0] != "torchcal":
                    continue
                for a in child.names:
                    sub = f"{base}.{a.name}"
                    out.add(sub if sub in modules else base)
            visit(child)

    visit(tree)
    out.discard(me)
    return out


def graph() -> dict[str, set[str]]:
    files = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: imports(p, set(files)) for m, p in files.items()}


def rank(u: str) -> int | None:
    for i, layer in enumerate(LAYERS):
        if u in layer:
            return i
    return None


def test_every_unit_has_a_layer():
    units = {unit(m) for m in graph()}
    missing = sorted(u for u in units if u != TOP and u not in LEAVES and rank(u) is None)
    assert not missing, f"modules of torchcal/ in no layer of tests/test_layers.py: {missing}"


def test_no_import_from_a_lower_layer_into_a_higher_one():
    bad = []
    for m, deps in graph().items():
        u = unit(m)
        for d in deps:
            v = unit(d)
            if v == TOP:
                bad.append(f"{m} imports the torchcal package itself ({d}): import the module it needs")
            elif u in LEAVES:
                if v not in LEAVES:
                    bad.append(f"{m} (a leaf utility) imports {d}")
            elif u != TOP and v not in LEAVES and rank(v) > rank(u):
                bad.append(f"{m} (layer {rank(u)}: {u}) imports {d} (layer {rank(v)}: {v})")
    assert not bad, "imports against the layer order:\n" + "\n".join(sorted(bad))


def test_no_import_cycle():
    g = graph()
    # subpackage __init__ modules re-export their members: an edge into a package means an edge into its members
    # only where they are imported, so the cycle check runs on modules as written
    state: dict[str, int] = {}
    cycles = []

    def dfs(m, stack):
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if d not in g:
                continue
            if state.get(d) == 1:
                cycles.append(" -> ".join(stack[stack.index(d) :] + [d]))
            elif d not in state:
                dfs(d, stack)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            dfs(m, [])
    assert not cycles, "import cycles in torchcal/:\n" + "\n".join(cycles)


def test_the_checker_sees_an_upward_import(tmp_path):
    f = tmp_path / "torchcal" / "robot" / "x.py"
    f.parent.mkdir(parents=True)
    f.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from torchcal.pipeline import Options\n"
        "def f():\n    from torchcal.pipeline.run import calibrate\n"
    )
    global PACKAGE
    old, PACKAGE = PACKAGE, tmp_path / "torchcal"
    try:
        # the type-only import counts as much as the one inside the function
        assert imports(f, {"torchcal.pipeline.run"}) == {"torchcal.pipeline", "torchcal.pipeline.run"}
    finally:
        PACKAGE = old


def test_torchcal_calibrate_is_the_pipeline_function():
    import torchcal
    from torchcal.pipeline import calibrate

    assert torchcal.calibrate is calibrate
