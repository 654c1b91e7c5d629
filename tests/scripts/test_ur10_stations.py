"""scripts/ur10_stations.py on a small subset of the real UR10 data (skipped where the data set is absent)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("TORCHCAL_IPA_DATA", ROOT.parent / "shared" / "data" / "real" / "ur10-ipa"))


@pytest.mark.skipif(
    not (DATA / "Series_D").is_dir(),
    reason=f"the ipa-robot-accuracy UR10 data set is not at {DATA} (set TORCHCAL_IPA_DATA to its folder)",
)
@pytest.mark.slow
def test_series_together_subset():
    """Series C and D together, kinematic: two stations and two probes, each series' held-out error near its own."""
    r = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "ur10_stations.py"), str(DATA), "--series", "C,D",
         "--methods", "kinematic", "--json"],
        capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["stations"] == ["C", "D"] and res["probes"] == ["T1", "T2"]
    kin = res["methods"]["kinematic"]
    for s in ("C", "D"):
        p = kin["per_series"][s]
        assert p["n_holdout"] > 0 and p["joint_mm"] < 1.3 * p["alone_mm"], (s, p)
    lever = kin["lever_arms_mm"]
    assert 80 < abs(lever["T1"][2]) < 110, lever  # the T-Mac of A-C, about 93 mm along the flange axis
    assert "C->D" in kin["across"]
