"""scripts/bench_ekf.py on a short trajectory: the last-line JSON with its keys, the three passes giving the same
predictions, and the caller's thread count restored."""

import contextlib
import importlib.util
import io
import json
from pathlib import Path

import torch

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "bench_ekf.py"


def test_json_keys_and_the_passes_agree():
    spec = importlib.util.spec_from_file_location("bench_ekf_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    stdout = io.StringIO()
    threads = torch.get_num_threads()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        returned = module.main(["--samples", "120", "--json"])
    assert torch.get_num_threads() == threads
    result = json.loads(stdout.getvalue().strip().splitlines()[-1])
    assert result == returned
    assert list(result) == [
        "pass_s",
        "module_pass_s",
        "module_ratio",
        "module_max_abs_diff_m",
        "pass_cpu_s",
        "module_pass_cpu_s",
        "repeat",
        "baseline_pass_s",
        "speedup",
        "max_abs_diff_m",
        "samples",
        "state_dim",
        "device",
        "threads",
        "status",
    ]
    assert result["samples"] == 120 and result["state_dim"] == 296 and result["threads"] == 1
    assert result["repeat"] == 3 and result["pass_cpu_s"] > 0 and result["module_pass_cpu_s"] > 0
    assert result["status"] == "ok"
    assert result["module_max_abs_diff_m"] < 1e-12 and result["max_abs_diff_m"] < 1e-12
