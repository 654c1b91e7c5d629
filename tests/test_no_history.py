"""No measurement history in torchcal's source: a comment or docstring says why the code is as it is; what happened
in some run (timings, results of a round of work, issue numbers, dates) belongs in commit messages and docs.

The check is a list of phrases that only such history uses, matched case-insensitively on every line of every .py
file under torchcal/ (the experiment code lives outside the package, in experiments/, and reports what it measured).
"""

import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchcal"
#: paths under torchcal/ not scanned (none: the experiments, whose output is their measurements, are outside it)
EXCLUDED: set[str] = set()

#: phrases of measurement history
HISTORY = [
    r"\bthis round\b",  # "the menu's form of the same name this round"
    r"\b(last|earlier|previous|later) rounds?\b",
    r"\bin our (trials|runs|tests|experiments|measurements)\b",
    r"\bwe (measured|found|saw|observed|tried|timed)\b",
    r"\bmeasured: \d",  # "(measured: 190 s instead of 17 s ...)"
    r"\bmeasured (faster|slower)\b",
    r"\bissue \d",  # "(issue 14.3)", "issue 5's targets"
    r"\bstop \d",
    r"\bload average\b",
    r"\binstead of \d+(\.\d+)? ?(s|ms|min)\b",
    r"\b\d+(\.\d+)? to \d+(\.\d+)? ?(mm|um|s)\b",  # "from 0.090 to 0.104 mm": a result's before and after
    r"\btook (about )?(twice|\d)",
    r"\btwice as (fast|long|slow)\b",
    r"\bon one [\w-]+ run\b",  # "(1.6e44 on one outside-style run)"
    r"\bon (the|an?) outside[\w -]*?(runs?|trajector(y|ies)|campaigns?)\b",  # "on the outside test campaigns"
    r"\bseries [a-z] (default )?run\b",
    r"\bfrom \d+ iterations into \d+\b",
    r"\b(doubled|halved|tripled) the\b",
    r"\b20\d\d-[01]\d-[0-3]\d\b",  # a date
]
PATTERN = re.compile("|".join(f"(?:{p})" for p in HISTORY), re.IGNORECASE)


def _skipped(rel: str, prefixes: set[str]) -> bool:
    return any(rel == p or rel.startswith(p + "/") for p in prefixes)


def history_lines(root: Path, skip: set[str]) -> list[str]:
    """``file:line: text`` of every line of a .py file under ``root`` (paths relative to its parent, those under
    ``skip`` left out) that carries a phrase of :data:`HISTORY`."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        if _skipped(rel, skip):
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if PATTERN.search(line):
                out.append(f"{rel}:{n}: {line.strip()}")
    return out


def test_no_measurement_history_in_comments_or_docstrings():
    found = history_lines(PACKAGE, EXCLUDED)
    assert not found, (
        "measurement history in torchcal/ (say why the code is as it is; the history goes into the commit "
        "message or docs):\n" + "\n".join(found)
    )


def test_the_scan_sees_a_planted_line(tmp_path):
    root = tmp_path / "torchcal"
    (root / "pipeline").mkdir(parents=True)
    (root / "experiments").mkdir()
    (root / "a.py").write_text(
        "x = 1  # the step that rounds down\n"
        'def f():\n    """Two threads are slower (Measured: 190 s instead of 17 s)."""\n'
        "# earlier rounds kept it; see Issue 14.3\n"
    )
    (root / "pipeline" / "b.py").write_text("# In our trials the error fell from 0.090 to 0.104 mm\n")
    (root / "experiments" / "c.py").write_text("# issue 5, item 5\n")
    skip = {"torchcal/experiments"}
    assert history_lines(root, skip) == [
        'torchcal/a.py:3: """Two threads are slower (Measured: 190 s instead of 17 s)."""',
        "torchcal/a.py:4: # earlier rounds kept it; see Issue 14.3",
        "torchcal/pipeline/b.py:1: # In our trials the error fell from 0.090 to 0.104 mm",
    ]
    # an exclusion hides its path and nothing else
    assert history_lines(root, skip | {"torchcal/pipeline"}) == history_lines(root, skip)[:2]


def test_pending_and_excluded_paths_exist():
    # an entry that names nothing (a module moved or renamed) would hide nothing and mislead
    for rel in EXCLUDED:
        assert (PACKAGE.parent / rel).exists(), rel
