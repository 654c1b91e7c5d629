"""Does a run's report tell one story? report.md and the terminal read against report.json.

A run directory's report.json holds the numbers; report.md says them in words and the terminal prints the first of
them. :func:`contradictions` reads the three and lists every statement that disagrees with report.json: a global
test called passed in one and failed in the other, a section on unexplained structure beside a global test that
passed, an RMSE printed with other digits, a decision's p-value other than the one report.json gives it (or without
the name of its test), an effect parameter without its unit, a candidate the terminal said it was validating with no
outcome. The tests run it on every report they generate; a user can run it on a run of their own.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

from torchcal.diagnose.score import named_p


def contradictions(run_dir: str | os.PathLike, terminal: str | None = None) -> list[str]:
    """Statements of ``run_dir``'s report.md (and of ``terminal``, the text calibrate or demo printed, where given)
    that disagree with its report.json, in words; empty when the report tells one story.

    Args:
        run_dir: a run directory written by ``torchcal calibrate`` (or the ``run`` folder of ``torchcal demo``).
        terminal: stdout and stderr of the command that wrote it, or None to read the files only.
    """
    run_dir = Path(run_dir)
    report = json.loads((run_dir / "report.json").read_text(encoding="utf-8"))
    md = (run_dir / "report.md").read_text(encoding="utf-8")
    found = _global_test(report, md) + _rmse(report, md) + _decisions(report, md) + _effects(report, md)
    found += [f"report.md lacks report.json's note {n!r}" for n in report["notes"] if f"- {n}" not in md]
    if terminal is not None:
        found += _terminal(report, terminal)
    return found


def _global_test(report: dict, md: str) -> list[str]:
    gt = report["global_test"]
    verdict = "passed" if gt["passed"] else "failed"
    out = []
    said = re.findall(r"Variance factor [\d.]+ against the bound [\d.]+ .*?\*\*(passed|failed)\*\*", md)
    if said != [verdict]:
        out.append(f"report.md's global test says {said}, report.json's: {verdict}")
    if gt["passed"] and report["unexplained"]:
        out.append("report.json lists unexplained structure, but its global test passed")
    if ("## Unexplained structure" in md) != bool(report["unexplained"]):
        out.append("report.md's 'Unexplained structure' section and report.json's 'unexplained' disagree")
    if gt["passed"] and "global test fails" in md:
        out.append("report.md says the global test fails; report.json: passed")
    return out


def _rmse(report: dict, md: str) -> list[str]:
    want = (
        f"Before: {report['rmse_before_mm']:.4f} mm; after the geometric fit: {report['rmse_geometric_mm']:.4f} mm; "
        f"final: {report['rmse_after_mm']:.4f} mm."
    )
    return [] if want in md else [f"report.md does not say report.json's held-out RMSEs ({want!r})"]


def _decisions(report: dict, md: str) -> list[str]:
    """Every decision of the loop in report.md with the p-value and test report.json give it, and its verdict."""
    out = []
    for d in (report.get("diagnosis") or {}).get("decisions") or []:
        verdict = "accepted" if d["accepted"] else "rejected"
        line = f"{d['name']} ({named_p(d['score'])}): **{verdict}**"
        if line not in md:
            out.append(f"report.md lacks the decision {line!r} of report.json")
    return out


def _effects(report: dict, md: str) -> list[str]:
    """Each fitted effect parameter with a value has a unit in report.json, and report.md prints both."""
    from torchcal.report.markdown import effect_params_words

    out = []
    for e in report["effects"]:
        params = {k: v for k, v in e["params"].items() if isinstance(v, dict) and "value" in v}
        out += [f"report.json: {e['kind']}'s parameter {k} has no unit" for k, v in params.items() if not v.get("unit")]
        words = effect_params_words(params)
        if words and words not in md:
            out.append(f"report.md does not print {e['kind']}'s parameters as {words!r}")
    return out


#: the calibrate command's last lines: the held-out RMSEs of report.json's stages
_HELD_OUT = re.compile(r"held-out RMSE: nominal ([\d.]+) mm, geometric ([\d.]+) mm, final ([\d.]+) mm")
_VALIDATING = re.compile(r"diagnosis round (\d+): (\S+) \((.*?)\): validating")


def _terminal(report: dict, text: str) -> list[str]:
    out = []
    m = _HELD_OUT.search(text)
    if m is not None:
        want = tuple(f"{report[k]:.4f}" for k in ("rmse_before_mm", "rmse_geometric_mm", "rmse_after_mm"))
        if m.groups() != want:
            out.append(f"the terminal's held-out RMSEs {m.groups()} differ from report.json's {want}")
    lines = text.splitlines()
    for i, line in enumerate(lines):
        v = _VALIDATING.search(line)
        if v is None:
            continue
        rnd, name, _ = v.groups()
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if not re.search(rf"diagnosis round {rnd}: {re.escape(name)}: (confirmed|not confirmed|rejected)", nxt):
            out.append(f"the terminal says it is validating {name} (round {rnd}) and gives no outcome")
    said = {v.groups() for v in map(_VALIDATING.search, lines) if v is not None}
    for d in (report.get("diagnosis") or {}).get("decisions") or [] if said else []:
        if (str(d["round"]), d["name"], named_p(d["score"])) not in said:
            out.append(f"the terminal never gives round {d['round']}'s {d['name']} as ({named_p(d['score'])})")
    if "global test failed" in text and report["global_test"]["passed"]:
        out.append("the terminal says the global test failed; report.json: passed")
    return out


__all__ = ["contradictions"]
