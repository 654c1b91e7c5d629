"""scripts/trajectory_outside.py on a tiny outside-style campaign: one JSON line with both methods on the
continuation, never worse than geometry alone, and the evidence of the choice."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "trajectory_outside.py"


def test_tiny_campaign(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--seeds", "0", "--fields", "tanh", "--samples", "800"]
        + ["--periods", "2000", "9000", "--json", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
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
