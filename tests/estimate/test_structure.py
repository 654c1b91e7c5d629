"""The package reads as its steps (issue 36, the estimator and the simulator first): no function over 80 lines, the
commands' parsers included (one module per command since issue 48), and ``solve`` takes ``trajectory`` by name (a
bare positional True said nothing at its call sites)."""

import ast
import inspect
from pathlib import Path

from torchcal.estimate.fit import solve

PACKAGE = Path(__file__).resolve().parents[2] / "torchcal"
LONGEST = 80


def test_no_function_over_80_lines_in_the_package():
    long = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > LONGEST:
                    long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_solve_takes_trajectory_by_name():
    assert inspect.signature(solve).parameters["trajectory"].kind is inspect.Parameter.KEYWORD_ONLY
