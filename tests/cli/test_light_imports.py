"""predict, compensate and plan on a finished run do not import the pipeline: its stages, the filters and the
diagnosis are a few tenths of a second of every such command (issue 37's 5x for predict) for code they never run.
Each command in a fresh interpreter, so that nothing else has imported them."""

import json
import subprocess
import sys

CODE = """
import json, sys
from torchcal.cli import main
codes = [main(a) for a in json.loads(sys.argv[1])]
heavy = sorted(m for m in sys.modules if m.startswith(("torchcal.pipeline", "torchcal.filter", "torchcal.diagnose")))
print(json.dumps({"codes": codes, "heavy": heavy}))
"""


def test_predict_compensate_and_plan_leave_the_pipeline_unloaded(run_dir, campaign, tmp_path):
    targets = tmp_path / "targets.csv"
    rows = (campaign / "test.csv").read_text().splitlines()
    targets.write_text("\n".join([r for r in rows if not r.startswith("#")][:4]) + "\n")
    commands = [
        ["predict", str(run_dir), str(campaign / "test.csv"), "--out", str(tmp_path / "p.csv")],
        ["compensate", str(run_dir), str(targets), "--out", str(tmp_path / "j.csv"), "--quiet"],
        [
            "plan",
            "--run",
            str(run_dir),
            "--robot",
            "ur5",
            "--n",
            "5",
            "--pool",
            "200",
            "--out",
            str(tmp_path / "n.csv"),
        ],
    ]
    for cmd in commands:
        proc = subprocess.run([sys.executable, "-c", CODE, json.dumps([cmd])], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-3000:]
        result = json.loads(proc.stdout.strip().splitlines()[-1])
        assert result["codes"] == [0], (cmd[0], proc.stderr[-2000:])
        assert result["heavy"] == [], f"{cmd[0]} imported {result['heavy']}"
