"""experiments.common (every script's --threads / --json) and the closed loop's target bookkeeping
(experiments.loop_targets), without running a calibration."""

import json

import pytest
import torch

from experiments import common, loop_targets
from torchcal._threads import torch_threads


def test_run_pins_the_threads_and_restores_the_callers():
    ap = common.parser("A test script.\n\nMore text.")
    ap.add_argument("--seed", type=int, default=0)
    seen = []
    with torch_threads(2):  # the caller's count, restored after the run
        args, result = common.run(ap, lambda a: seen.append(torch.get_num_threads()) or a.seed * 2, ["--seed", "3"])
        assert torch.get_num_threads() == 2
    assert (result, seen, args.threads, args.json) == (6, [1], 1, False)


@pytest.mark.parametrize(
    "argv, plain, lines",
    [(["--json"], {"x": 1}, ['{"a": [1, 2]}']), ([], {"x": 1}, ["{", ' "x": 1', "}"]), ([], None, [])],
)
def test_emit_prints_one_line_with_json_the_plain_view_without(capsys, argv, plain, lines):
    args = common.parser("doc").parse_args(argv)
    common.emit({"a": [1, 2]}, args, plain=plain)
    assert capsys.readouterr().out.splitlines() == lines


def _row(group, loop, true_form=None, geometric=0.05, correct=True, found=("x",)):
    return {
        "group": group,
        "loop_mm": loop,
        "true_form_mm": true_form,
        "geometric_mm": geometric,
        "oracle_mm": 0.01,
        "correct": correct,
        "found": list(found),
        "meets_target": False,
    }


def test_verdicts_follow_the_issues_targets():
    assert loop_targets.verdict("single", _row("single", 0.0119, true_form=0.01))
    assert not loop_targets.verdict("single", _row("single", 0.0121, true_form=0.01))
    assert not loop_targets.verdict("single", _row("single", 0.01, true_form=0.01, correct=False))
    assert loop_targets.verdict("three", _row("three", 0.040)) and not loop_targets.verdict(
        "three", _row("three", 0.041)
    )
    assert loop_targets.verdict("field", _row("field", 0.05)) and not loop_targets.verdict(
        "field", _row("field", 0.051)
    )
    assert loop_targets.verdict("clean", _row("clean", 0.05, found=()))
    assert not loop_targets.verdict("clean", _row("clean", 0.05, found=("cyclic",)))
    assert not loop_targets.verdict("clean", _row("clean", 0.0501, found=()))


def test_cases_cover_every_group_and_seed_and_summaries_count_them():
    cases, tags = loop_targets.cases(2, 300, 10)
    assert len(cases) == 2 * sum(len(v) for v in loop_targets.GROUPS.values()) == len(tags)
    assert {c["seed"] for c in cases} == {10, 11} and all(c["poses"] == 300 for c in cases)
    assert cases[tags.index("clean")]["effects"] == []
    rows = [_row("single", 0.02, true_form=0.01), _row("single", 0.03, true_form=0.02, correct=False)]
    rows[0]["meets_target"] = True
    s = loop_targets.summarise("single", rows)
    assert (s["runs"], s["meets_target"], s["named_right"]) == (2, 1, 1)
    assert s["loop_mm_mean"] == pytest.approx(0.025) and s["loop_mm_max"] == 0.03
    assert s["ratio_to_true_form_max"] == pytest.approx(2.0)
    assert json.loads(json.dumps(s)) == s


#: the scripts whose seeds are independent fits, and the positional arguments each needs
SWEEPS = {
    "restation": ["DATA"],
    "prior_update": ["DATA"],
    "plan_poses": ["DATA"],
    "false_positives": [],
    "detection_limits": [],
    "closed_loop": [],
    "couplings": [],
    "instrument_effects": [],
}


def test_the_seed_sweeps_run_one_after_another_unless_given_workers_or_an_address(monkeypatch):
    import argparse
    import runpy
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[2] / "scripts"
    monkeypatch.syspath_prepend(str(scripts))
    for name, positional in SWEEPS.items():
        found = runpy.run_path(str(scripts / f"{name}.py"), run_name="__check__")
        (ap,) = [v for v in found.values() if isinstance(v, argparse.ArgumentParser)]
        assert (ap.parse_args(positional).workers, ap.parse_args(positional).address) == (None, None), name
        a = ap.parse_args([*positional, "--workers", "2", "--address", "auto"])
        assert (a.workers, a.address) == (2, "auto"), name


def test_the_coupling_grid_covers_every_adjacent_pair_and_judges_name_and_error():
    from experiments import couplings

    quick = couplings.cases(False, 500, 2, 800)
    assert [c["effects"] for c in quick[:5]] == [
        ["coupling:2<-1=0.0002"],
        ["coupling:3<-2=0.0006"],
        ["coupling:4<-3=0.002"],
        ["coupling:5<-4=0.0002"],
        ["coupling:6<-5=0.0006"],
    ]
    assert [c["effects"] for c in quick[5:]] == [[], []] and len({c["seed"] for c in quick}) == 7
    full = couplings.cases(True, 500, 20, 800)
    assert len(full) == 10 * 3 + 20 and {e for c in full for e in c["effects"]} >= {"coupling:5<-6=0.002"}
    row = {"effects": ["coupling:5<-4=0.001"], "correct": True, "loop_mm": 0.030, "true_form_mm": 0.025}
    assert couplings.verdict(row) and not couplings.verdict({**row, "loop_mm": 0.0301})
    assert not couplings.verdict({**row, "correct": False})
    assert couplings.verdict({"effects": [], "found": []}) and not couplings.verdict({"effects": [], "found": [1]})


def test_the_instrument_grid_covers_every_harmonic_and_term_and_judges_name_and_error():
    from experiments import instrument_effects as ie

    full = ie.cases(ie.grid(True, None), 700, 20, 800, 3)
    specs = {e for c in full for e in c["effects"]}
    assert {f"tracker_{a}:{h}={u}urad" for a in ("az", "el") for h in range(1, 9) for u in (20, 40, 60)} <= specs
    assert {
        "range_offset=50um",
        "range_scale=10ppm",
        "axis_tilt=60urad",
        "beam_tilt=20urad",
        "beam_offset=50um",
    } <= specs
    assert sum(1 for c in full if not c["effects"]) == 20 and all(c["stations"] == 3 for c in full)
    assert len({c["seed"] for c in full}) == len(full)
    assert ie.grid(False, ["axis_tilt=20urad"]) == ["axis_tilt=20urad"]
    row = {
        "effects": ["tracker_az:3=40urad"],
        "truth_names": ["instrument:azimuth:3"],
        "found_names": ["instrument:azimuth:3"],
        "found": [["instrument", None]],
        "truth_rms_um": [40.0],
        "loop_mm": 0.030,
        "true_form_mm": 0.025,
    }
    assert ie._row(row)["meets_target"] and not ie._row({**row, "loop_mm": 0.0301})["meets_target"]
    assert not ie._row({**row, "found_names": ["instrument:azimuth:4"]})["meets_target"]
    # a neighbouring order the run itself calls a guess among the true one: not named right, but among the alike
    guess = ie._row({**row, "found_names": ["instrument:azimuth:4"], "found_alike": ["instrument:azimuth:3"]})
    assert not guess["named_right"] and guess["named_among_alike"]
    assert not ie._row({**row, "found_names": ["instrument:azimuth:4"], "found_alike": []})["named_among_alike"]
    # a range scale is held, never named: its target is no name and the error within 1.2 x
    held = {
        **row,
        "effects": ["range_scale=10ppm"],
        "truth_names": ["instrument:scale"],
        "found_names": [],
        "found": [],
    }
    assert ie._row(held)["meets_target"] and not ie._row({**held, "found_names": ["instrument:range"]})["meets_target"]
