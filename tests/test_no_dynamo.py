"""A default calibration never imports ``torch._dynamo`` (issue 14: the import, with sympy, ``torch.distributed``
and ``torch.onnx``, is a large share of a default run's time and memory, for nothing).

Two things pulled it in: torch's arithmetic between a forward-mode tangent and a constant (the estimators'
Jacobians; :mod:`torchcal._dual`) and constructing a ``torch.optim`` optimizer (the GP's hyperparameters;
:mod:`torchcal._lbfgs`). The run is the golden ``auto`` run's campaign (a compliance the diagnosis names and a
smooth field the learned stage takes), in a fresh interpreter so that nothing else has imported it.
"""

import json
import subprocess
import sys

import pytest

CODE = """
import json, sys
from torchcal._threads import torch_threads
from torchcal.pipeline import Options, calibrate
from torchcal.sim import EffectSpec, SimConfig, simulate

effects = [EffectSpec.parse("compliance:2=60um"), EffectSpec.parse("field=0.05mm")]
cfg = SimConfig(robot="ur5", poses=200, test_poses=20, seed=7, effects=effects)
with torch_threads(1):
    campaign = simulate(cfg)
    before = "torch._dynamo" in sys.modules
    run = calibrate("ur5", campaign.train, Options(seed=7))
print(json.dumps({"before": before, "after": "torch._dynamo" in sys.modules,
                  "effects": [e.kind for e in run.effects]}))
"""


@pytest.mark.slow
def test_default_calibration_does_not_import_dynamo():
    proc = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # the run went through the paths that imported it: a named joint effect (its Jacobians in forward mode, the
    # diagnosis's score tests) and the learned stage (its hyperparameters by L-BFGS)
    assert "compliance" in result["effects"] and "learned" in result["effects"], result
    assert not result["before"]
    assert not result["after"], "a default calibration imported torch._dynamo"


ORIENTATION = """
import json, sys
from torchcal._threads import torch_threads
from torchcal.pipeline import Options, calibrate
from torchcal.sim import SimConfig, simulate
with torch_threads(1):
    campaign = simulate(SimConfig(robot="ur5", poses=30, test_poses=0, seed=1, orientation_sigma_deg=0.01))
    run = calibrate("ur5", campaign.train, Options(method="kinematic", seed=1))
print(json.dumps({"after": "torch._dynamo" in sys.modules}))
"""


@pytest.mark.slow
def test_calibration_of_a_6d_probe_does_not_import_dynamo():
    """A 6-D probe's rows whiten their orientation with the joint noise turning the probe (its joint Jacobian),
    which a forward-mode pass through the chain computed, importing torch._dynamo."""
    proc = subprocess.run([sys.executable, "-c", ORIENTATION], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert not json.loads(proc.stdout.strip().splitlines()[-1])["after"], "a 6-D calibration imported torch._dynamo"
