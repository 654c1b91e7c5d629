"""The orchestration layers call their helpers by keyword: no function in torchcal/pipeline or torchcal/diagnose
takes more than :data:`MAX_POSITIONAL` positional parameters (``self`` and ``cls`` not counted). Past a handful, a
call reads as a row of values whose meaning is its position, and two of one type (the errors with and without an
effect, the fitting and validation indices) swap without an error. Read from the source (``ast``)."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchcal"
#: the most positional parameters a function of the checked packages takes; the rest are keyword-only
MAX_POSITIONAL = 6
CHECKED = ("pipeline", "diagnose")


def too_many_positional(source: str) -> list[tuple[int, str, int]]:
    """``(line, name, count)`` of every function in ``source`` with more than :data:`MAX_POSITIONAL` positional
    parameters."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            args = [*node.args.posonlyargs, *node.args.args]
            count = len(args) - (1 if args and args[0].arg in ("self", "cls") else 0)
            if count > MAX_POSITIONAL:
                out.append((node.lineno, node.name, count))
    return out


def test_the_scan_finds_a_long_positional_signature():
    assert too_many_positional("def f(a, b, c, d, e, f, g): pass") == [(1, "f", 7)]
    assert too_many_positional("class C:\n    def m(self, a, b, c, d, e, f, *, g): pass") == []


def test_no_helper_of_the_orchestration_layers_takes_more_than_six_positional_parameters():
    found = [
        f"{path.relative_to(PACKAGE.parent)}:{line} {name} ({count} positional)"
        for pkg in CHECKED
        for path in sorted((PACKAGE / pkg).rglob("*.py"))
        for line, name, count in too_many_positional(path.read_text(encoding="utf-8"))
    ]
    assert not found, "make the parameters past the sixth keyword-only: " + "; ".join(found)
