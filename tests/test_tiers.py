"""The two tiers of the suite: ``make test`` leaves out the tests marked ``slow``, ``make test-all`` (what CI runs)
runs every test; the fast tier still reaches every part of the package, and no test asserts a wall time (machines
here differ 3-4x from one session to the next: speed is measured by scripts that print ratios, not by tests)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
CLOCKS = {"perf_counter", "monotonic", "time", "process_time", "perf_counter_ns", "monotonic_ns", "time_ns"}


def _target(name: str) -> str:
    """The recipe of the Makefile's target ``name``, its lines joined."""
    text = (ROOT / "Makefile").read_text(encoding="utf-8")
    m = re.search(rf"^{re.escape(name)}:[^\n]*\n((?:\t[^\n]*\n)+)", text, flags=re.M)
    assert m, f"the Makefile has no target {name!r}"
    return m.group(1)


def test_make_test_is_the_fast_tier_and_ci_runs_every_test():
    fast, every = _target("test"), _target("test-all")
    assert "pytest" in fast and '-m "not slow"' in fast
    assert "pytest" in every and "slow" not in every
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r"^make test-all$", ci, flags=re.M), ".ci/run must run every test"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "make test" in readme and "make test-all" in readme


def _is_slow(decorators: list[ast.expr]) -> bool:
    """The function as a whole is marked slow (a parameter marked slow leaves the others in the fast tier)."""
    return any(ast.unparse(d) == "pytest.mark.slow" for d in decorators)


def _tests(path: Path) -> tuple[int, int]:
    """(tests, tests marked slow) of a test file, counted by function; a module-level ``pytestmark`` with ``slow``
    marks them all."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    module_slow = any(
        isinstance(node, ast.Assign)
        and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)
        and "slow" in ast.unparse(node.value)
        for node in tree.body
    )
    funcs = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")]
    slow = sum(module_slow or _is_slow(f.decorator_list) for f in funcs)
    return len(funcs), slow


def test_the_fast_tier_reaches_every_part_of_the_package():
    """Each folder of tests/ (one per subpackage of torchcal) keeps tests outside the slow tier."""
    folders = sorted(p for p in TESTS.iterdir() if p.is_dir() and any(p.glob("test_*.py")))
    assert len(folders) >= 8
    for folder in folders:
        counts = [_tests(f) for f in folder.rglob("test_*.py")]
        total, slow = sum(c[0] for c in counts), sum(c[1] for c in counts)
        assert total > slow, f"tests/{folder.name}: every test is marked slow; the fast tier would not reach it"
    assert sum(_tests(f)[1] for f in TESTS.rglob("test_*.py")) >= 20, "the slow tier is nearly empty"


def _clock_calls(node: ast.AST) -> list[str]:
    return [
        ast.unparse(n)
        for n in ast.walk(node)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr in CLOCKS
    ]


def test_no_test_asserts_a_wall_time():
    """An assert that reads a clock, or compares a name the test set from one, is a timed unit test."""
    for path in sorted(TESTS.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        timed = {
            t.id
            for node in ast.walk(tree)
            if isinstance(node, ast.Assign) and _clock_calls(node.value)
            for t in node.targets
            if isinstance(t, ast.Name)
        }
        for node in ast.walk(tree):
            if not isinstance(node, ast.Assert):
                continue
            names = {n.id for n in ast.walk(node.test) if isinstance(n, ast.Name)}
            assert not _clock_calls(node.test) and not (names & timed), (
                f"{path.relative_to(ROOT)}:{node.lineno}: asserts a wall time"
            )
