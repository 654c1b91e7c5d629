"""report.json unchanged for the same seed: a fresh small run against the stored golden report.

The golden reports and the code that regenerates them are in ``tests/golden/`` (see its module
docstring). What is compared how (:func:`differences`):

* Discrete results exactly: the structure (keys, list lengths), strings, booleans, None and integers
  (counts, joints, iterations, ranks): which effects, decisions, stages, fixed parameters and notes.
* Numbers to :data:`REL` = 1e-4 of the quantity, or of its standard deviation where the report gives one
  beside it (``std``, ``sigma`` or ``se`` in the same object, element by element for lists), with an absolute
  :data:`ABS` for values at zero. Why 1e-4: the same run differs between BLAS kernels (AVX-512, AVX2,
  ``MKL_CBWR=COMPATIBLE``) by rounding amplified by the conditioning and cut off by the solvers' own stops.
  Measured on the golden runs when this tolerance was chosen: held-out RMSEs and the tracker pose by 1e-8,
  training RMSEs of the learned stage by 1e-7, a parameter by at most 1e-6 of its standard deviation (8e-7; its
  own value moves more where it is a fraction of a sigma, hence the std as the scale), the localisation's
  smoothing (a GCV search over lambda that stops at about 1e-6) by 4e-6 in its edf and reference dof. 1e-4 is 30
  times above the largest of these and statistically invisible (1e-4 sigma), while a change of the method moves
  numbers by far more: a 1 % change fails (:func:`test_a_different_report_is_flagged`).
* p-values on the log scale, to REL of ``max(1, |ln p|)``: ``ln p`` is about ``-statistic / 2``, so it carries
  the statistic's relative precision, while p itself magnifies it (a p of 1e-47 moved by 1e-4 of itself between
  kernels, 2e-6 of its logarithm).
* Round-off quantities: the ``independence`` of an exact linear dependence is rounding (1e-17 to 1e-15, another
  value per kernel); below :data:`ROUNDOFF` it compares as zero. The decision it feeds (a parameter held fixed,
  against a tolerance of 1e-6) compares exactly.
* Numbers inside strings (notes, reasons): the text around them compares exactly, integers exactly, decimals to
  one unit in their last printed digit or REL, and values below ROUNDOFF as zero (their own fields hold them).

Skipped keys: none so far (:data:`VOLATILE`; the report holds no timings and its one path, ``robot_spec``, is
the built-in name ``ur5`` here).
"""

import copy
import json
import math
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "golden"))
import golden  # noqa: E402

#: report keys whose values may differ between runs (timings, absolute paths), at any depth
VOLATILE: frozenset[str] = frozenset()
#: relative tolerance of a number, of its standard deviation where the report gives one (module docstring)
REL = 1e-4
#: absolute tolerance for values at zero (m, rad or mm), where a relative test means nothing
ABS = 1e-12
#: quantities below this are round-off (where named in :data:`ROUNDOFF_KEYS`, and inside strings)
ROUNDOFF = 1e-12
ROUNDOFF_KEYS = frozenset({"independence"})
#: keys holding tail probabilities, compared on the log scale
P_KEYS = frozenset({"p_value", "p_bonferroni"})
#: keys that give the standard deviation of the numbers beside them
STD_KEYS = ("std", "sigma", "se")
#: a number inside a string; digits glued to a word (``tau2``, ``q2_t``, ``chi2``) belong to the word
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _close(a: float, b: float, key: str | None, scale) -> bool:
    if key in P_KEYS:
        la, lb = math.log(max(a, 1e-300)), math.log(max(b, 1e-300))
        return abs(la - lb) <= REL * max(1.0, abs(la))
    if key in ROUNDOFF_KEYS and abs(a) < ROUNDOFF and abs(b) < ROUNDOFF:
        return True
    s = abs(scale) if isinstance(scale, int | float) and not isinstance(scale, bool) else 0.0
    return abs(a - b) <= max(REL * max(abs(a), s), ABS)


def _last_digit(text: str) -> float:
    """The value of one unit in the last printed digit of a decimal number: 0.0547 -> 1e-4, 1.5e-47 -> 1e-48."""
    mantissa, _, exponent = text.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (int(exponent or 0) - decimals)


def _string_differs(expected: str, got: str) -> bool:
    if expected == got:
        return False
    if NUMBER.sub("#", expected) != NUMBER.sub("#", got):
        return True
    for x, y in zip(NUMBER.findall(expected), NUMBER.findall(got)):
        if not any(c in x + y for c in ".eE"):  # integers: counts, joints, identifiers
            if int(x) != int(y):
                return True
            continue
        a, b = float(x), float(y)
        if abs(a) < ROUNDOFF and abs(b) < ROUNDOFF:
            continue
        if abs(a - b) > max(_last_digit(x), _last_digit(y), REL * abs(a)) * (1 + 1e-9):
            return True
    return False


def differences(expected, got, where: str = "report", key: str | None = None, scale=None) -> list[str]:
    """Every place where ``got`` differs from ``expected`` beyond the tolerances of the module docstring.

    Args:
        key: the name of the value in its object (chooses p-value and round-off rules).
        scale: the standard deviation given beside the value (a number, or a list beside a list).

    Returns:
        One line per difference, with its path; empty when the two agree.
    """
    if isinstance(expected, dict):
        if not isinstance(got, dict):
            return [f"{where}: expected an object, got {type(got).__name__}"]
        out = (
            [f"{where}: keys {sorted(set(expected) ^ set(got))} in only one of the two"]
            if set(expected) != set(got)
            else []
        )
        sd = next((expected[k] for k in STD_KEYS if k in expected), None)
        for k in expected:
            if k in got and k not in VOLATILE:
                out += differences(expected[k], got[k], f"{where}.{k}", k, None if k in STD_KEYS else sd)
        return out
    if isinstance(expected, list):
        if not isinstance(got, list) or len(got) != len(expected):
            return [f"{where}: expected a list of {len(expected)}, got {got!r:.200}"]
        scales = scale if isinstance(scale, list) and len(scale) == len(expected) else [scale] * len(expected)
        return [
            d
            for i, (a, b, sc) in enumerate(zip(expected, got, scales))
            for d in differences(a, b, f"{where}[{i}]", key, sc)
        ]
    if isinstance(expected, float) or (
        isinstance(expected, int) and not isinstance(expected, bool) and isinstance(got, float)
    ):
        if isinstance(got, bool) or not isinstance(got, int | float) or not _close(expected, got, key, scale):
            return [f"{where}: expected {expected!r}, got {got!r}"]
        return []
    if isinstance(expected, str) and isinstance(got, str):
        return [f"{where}: expected {expected!r}, got {got!r}"] if _string_differs(expected, got) else []
    return [] if expected == got and type(expected) is type(got) else [f"{where}: expected {expected!r}, got {got!r}"]


def test_differences_finds_a_changed_number_and_a_missing_key():
    a = {"x": 1.0, "y": [1, "a", {"z": None}]}
    assert differences(a, json.loads(json.dumps(a))) == []
    assert differences(a, {"x": 1.01, "y": [1, "a", {"z": None}]}) == ["report.x: expected 1.0, got 1.01"]
    assert len(differences(a, {"x": 1.0, "y": [1, "a", {}]})) == 1


def _perturbed(report, rel: float):
    """``report`` with every float moved by ``rel`` of itself (signs alternating), round-off independences
    replaced by other round-off and every decimal inside a string moved by one unit in its last digit."""
    sign = [1.0]

    def bump(text: str) -> str:
        if not any(c in text for c in ".eE"):
            return text
        return repr(float(text) + _last_digit(text)) if abs(float(text)) >= ROUNDOFF else "7.7e-16"

    def walk(x, key=None):
        if isinstance(x, dict):
            return {k: walk(v, k) for k, v in x.items()}
        if isinstance(x, list):
            return [walk(v, key) for v in x]
        if isinstance(x, float):
            if key in ROUNDOFF_KEYS and abs(x) < ROUNDOFF:
                return 3.3e-16
            sign[0] = -sign[0]
            return x * (1.0 + sign[0] * rel)
        if isinstance(x, str):
            return NUMBER.sub(lambda m: bump(m.group()), x)
        return x

    return walk(report)


@pytest.mark.parametrize("method", list(golden.CASES))
def test_kernel_sized_noise_passes(method):
    """Changes of the size the BLAS kernels make (here 1e-6 of every number, ten times what they did) pass."""
    expected = json.loads(golden.path(method).read_text(encoding="utf-8"))
    assert differences(expected, _perturbed(expected, 1e-6)) == []


def test_a_different_report_is_flagged():
    """A changed effect, decision, count, note or a 1 % change of a number is a difference."""
    expected = json.loads(golden.path("auto").read_text(encoding="utf-8"))
    assert expected["effects"][0]["kind"] == "compliance" and expected["effects"][0]["params"]["k"]["std"] > 0

    def flagged(edit) -> list[str]:
        got = copy.deepcopy(expected)
        edit(got)
        return differences(expected, got)

    def scale(obj, key, f):
        obj[key] *= f

    edits = {
        "an effect of another kind": lambda r: r["effects"][0].update(kind="cyclic"),
        "an effect left out": lambda r: r["effects"].pop(0),
        "another decision": lambda r: r["diagnosis"]["decisions"][1].update(accepted=True),
        "one more iteration": lambda r: r["fits"][0].update(iterations=r["fits"][0]["iterations"] + 1),
        "held-out RMSE 1 % higher": lambda r: scale(r, "rmse_after_mm", 1.01),
        "a parameter 1 % larger": lambda r: scale(r["parameters"]["estimated"][0], "value", 1.01),
        "an effect's size 1 % larger": lambda r: scale(r["effects"][0]["params"]["k"], "value", 1.01),
        "a score statistic 1 % larger": lambda r: scale(r["effects"][0]["evidence"], "statistic", 1.01),
        "a p-value ten times larger": lambda r: scale(r["effects"][0]["evidence"], "p_bonferroni", 10.0),
        "a note's number two units off": lambda r: r["notes"].__setitem__(
            0, re.sub(r"vs (\d\.\d{4})", lambda m: f"vs {float(m.group(1)) + 2e-4:.4f}", r["notes"][0], count=1)
        ),
        "a note's count changed": lambda r: r["notes"].__setitem__(
            5, r["notes"][5].replace("160 training", "161 training")
        ),
        "a fixed parameter's reason naming another": lambda r: r["parameters"]["fixed"][3].update(
            reason=r["parameters"]["fixed"][3]["reason"].replace("on d2", "on d3")
        ),
    }
    for what, edit in edits.items():
        assert flagged(edit), what
    # and one unit in a note's last printed digit is not (the same number, rounded the other way)
    assert flagged(lambda r: r["notes"].__setitem__(0, r["notes"][0].replace("0.0534", "0.0535"))) == []


@pytest.mark.slow
@pytest.mark.parametrize("method", list(golden.CASES))
def test_report_matches_the_golden_report(method):
    expected = json.loads(golden.path(method).read_text(encoding="utf-8"))
    got = golden.golden_report(method)
    diff = differences(expected, got)
    assert not diff, f"{len(diff)} differences from {golden.path(method).name}:\n" + "\n".join(diff[:30])


@pytest.mark.slow
def test_a_loaded_robot_gives_the_same_report_as_its_name():
    from torchcal._threads import torch_threads
    from torchcal.pipeline import Options, calibrate
    from torchcal.report.rundir import build_report
    from torchcal.robot import load_robot
    from torchcal.sim import SimConfig, simulate

    with torch_threads(1):
        c = simulate(SimConfig(robot="ur5", poses=120, test_poses=10, seed=3))
        by_name = build_report(calibrate("ur5", c.train, Options(method="kinematic", seed=3)))
        robot = load_robot("ur5")
        run = calibrate(robot, c.train, Options(method="kinematic", seed=3))
    assert run.robot_spec == robot.source
    # the run calibrates a copy: the robot passed stays nominal
    assert run.robot is not robot and all(float(g.delta.detach().abs().max()) == 0.0 for g in robot.groups().values())
    got = json.loads(json.dumps(build_report(run)))
    assert got.pop("robot_spec") == str(robot.source) and by_name.pop("robot_spec") == "ur5"
    assert differences(json.loads(json.dumps(by_name)), got) == []


def test_an_effects_reported_parameters_are_the_final_models():
    """An effect is recorded when it is admitted; the fits after it (the learned stage's refits) move its values, and
    report.json gives the final ones: the golden run's compliance k as its model holds it."""
    run = golden.golden_run("auto")
    (entry,) = [e for e in run.effects_report if e["kind"] == "compliance"]
    (effect,) = [e for e in run.model.effects if e.label() == entry["label"]]
    assert entry["params"]["k"]["value"] == float(effect.k.detach())
    assert entry["params"]["k"]["unit"] == "rad/(N m)"
