"""The estimator and the simulator read as their steps (issue 36): no function over 80 lines, and ``solve`` takes
``trajectory`` by name (a bare positional True said nothing at its call sites)."""

import ast
import inspect
from pathlib import Path

from torchcal.estimate.fit import solve

PACKAGE = Path(__file__).resolve().parents[2] / "torchcal"
LONGEST = 80


def test_no_function_over_80_lines_in_estimate_and_sim():
    long = []
    for folder in ("estimate", "sim"):
        for path in sorted((PACKAGE / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > LONGEST:
                        long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({lines} lines)")
    assert not long, long


def test_solve_takes_trajectory_by_name():
    assert inspect.signature(solve).parameters["trajectory"].kind is inspect.Parameter.KEYWORD_ONLY
