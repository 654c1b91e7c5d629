"""scripts/trajectory_outside.py on a tiny outside-style campaign: one JSON line with both methods on the
continuation, never worse than geometry alone, and the evidence of the choice."""

import subprocess
import sys

import pytest
from _cli import ROOT, run_script

SCRIPT = ROOT / "scripts" / "trajectory_outside.py"


@pytest.mark.slow
def test_tiny_campaign(tmp_path):
    res, _ = run_script(
        "trajectory_outside.py",
        *["--seeds", "0", "--fields", "tanh", "--samples", "800", "--periods", "2000", "9000"],
        *["--json", "--out", str(tmp_path)],
    )
    (row,) = res["rows"]
    assert (row["train"], row["test"], row["field"]) == (640, 160, "tanh")
    assert 0.0 < row["geometry_mm"] < 0.5 and row["ratio"] == row["integrated_mm"] / row["geometry_mm"]
    assert row["ratio"] <= 1.0 + 1e-9  # the case where geometry alone wins is the one the method must keep
    assert row["validation"][0]["candidate"] == "geometry alone" and len(row["validation"]) > 1
    assert row["chosen"] is not None
    assert res["summary"]["campaigns"] == 1 and res["summary"]["worst_ratio"] == row["ratio"]
    assert (tmp_path / "tanh-s0" / "truth.json").exists() and (tmp_path / "tanh-s0" / "test.csv").exists()


def test_bad_size_is_a_usage_error():
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--size", "0.1", "--json"], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert proc.returncode == 2 and "--size" in proc.stderr


def test_summary_flags_worse_and_miscovered_campaigns():
    from experiments.trajectory_outside import markdown, summary

    base = {"width": 29, "size_mm": 0.1, "geometry_mm": 0.1, "chosen": "x"}
    rows = [
        {**base, "seed": 0, "field": "tanh", "integrated_mm": 0.05, "ratio": 0.5, "coverage_2sigma": 0.95},
        {**base, "seed": 1, "field": "fourier", "integrated_mm": 0.15, "ratio": 1.5, "coverage_2sigma": 0.4},
        {**base, "seed": 2, "field": "product", "integrated_mm": 0.1, "ratio": 1.0 + 1e-12, "coverage_2sigma": None},
    ]
    s = summary(rows)
    assert s["worse_than_geometry"] == ["fourier-s1"]  # a gate faded to geometry: equal up to rounding, not worse
    assert s["coverage_outside_90_98"] == ["fourier-s1"] and s["worst_ratio"] == 1.5 and s["median_ratio"] > 1.0
    md = markdown(rows)
    assert "| fourier-s1 | 29 Fourier features, 0.1 mm | 0.1000 | 0.1500 | 1.500 | 40.0 % | x |" in md
    assert md.count("\n") == len(rows) + 1


def test_the_default_methods_table_when_asked():
    from experiments.trajectory_outside import markdown

    base = {"width": 29, "size_mm": 0.1, "geometry_mm": 0.1, "chosen": "x", "integrated_mm": 0.05, "ratio": 0.5}
    rows = [
        {
            **base,
            "seed": 0,
            "field": "tanh",
            "coverage_2sigma": 0.95,
            "geometry_training_part_mm": 0.1,
            "auto_mm": 0.1,
            "auto_ratio": 1.0,
        },
        {
            **base,
            "seed": 1,
            "field": "tanh",
            "coverage_2sigma": 0.95,
            "geometry_training_part_mm": 0.1,
            "auto_mm": 0.2,
            "auto_ratio": 2.0,
        },
    ]
    rows[0] |= {"auto_effects": [], "auto_holdout_guard": {"passed": False, "kept_stage": "geometric"}}
    rows[1] |= {"auto_effects": ["cyclic:5"], "auto_holdout_guard": {"passed": True}}
    md = markdown(rows)
    assert "| tanh-s0 | 0.1000 | 0.1000 | 1.000 | none | stepped back to geometric |" in md
    assert "| tanh-s1 | 0.1000 | 0.2000 | 2.000 | cyclic:5 | passed |" in md
    assert "default (auto)" in md and "default (auto)" not in markdown(
        [{k: v for k, v in r.items() if not k.startswith(("auto", "geometry_training"))} for r in rows]
    )
