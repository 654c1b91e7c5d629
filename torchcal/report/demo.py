"""The demo: the main job end to end on a simulated UR5 campaign with effects the nominal model lacks, what it writes
(the campaign, the run, ``summary.json``) and the table of errors before and after every step that it prints (the
README's, digit for digit). ``torchcal demo`` is these steps with its ``--out`` and ``--seed``."""

from __future__ import annotations

import json
from pathlib import Path

from torchcal.sim import EffectSpec, SimConfig

#: the effects the demo simulates and the nominal model does not declare
DEMO_EFFECTS = ("compliance:2=60um", "field=0.05mm")

#: the table's words for a stage (an effect's stage is ``+ its name``)
STAGE_LABELS = {
    "nominal": "nominal geometry (tracker, lever fitted)",
    "geometric": "after the kinematic calibration",
    "learned": "+ learned residual model",
}


def demo_config(seed: int = 0) -> SimConfig:
    """The demo's campaign: a UR5, 800 training and 200 test poses, :data:`DEMO_EFFECTS`."""
    return SimConfig(
        robot="ur5", poses=800, test_poses=200, seed=seed, effects=[EffectSpec.parse(e) for e in DEMO_EFFECTS]
    )


def write_demo(run, campaign, into: Path, out: Path) -> float:
    """Write the demo's campaign (``into/data``), its run (``into/run``) and ``into/summary.json``, whose paths name
    ``out`` (where ``into`` will be moved); returns the final model's RMSE [m] on the campaign's test file, as
    ``predict`` gives it from the written run."""
    from torchcal._outdir import mark
    from torchcal.report.rundir import write_run_files
    from torchcal.sim import write_campaign
    from torchcal.use.rundir import predict

    names = {k: p.name for k, p in write_campaign(campaign, into / "data").items()}
    (into / "run").mkdir()
    mark(into / "run", "calibrate")
    write_run_files(run, into / "run")
    p = predict(into / "run", campaign.test)
    test_rmse = float((p - campaign.test.p).norm(dim=-1).square().mean().sqrt())
    summary = {
        "data": {k: str(out / "data" / v) for k, v in names.items()},
        "run": str(out / "run"),
        "simulated": list(DEMO_EFFECTS),
        "holdout_rmse_mm": {s.name: s.rmse * 1e3 for s in run.stages},
        "test_file_rmse_mm": test_rmse * 1e3,
        "stages": [s.name for s in run.stages],
        "effects": [{"kind": e["kind"], "joint": e["joint"]} for e in run.effects_report],
    }
    (into / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return test_rmse


def demo_table(run, test_rmse: float) -> list[str]:
    """The demo's table: what it simulated, each stage's held-out RMSE and max [mm], the final model's RMSE on the
    test file, the effects found."""
    from torchcal.report.markdown import effect_line

    lines = [
        f"simulated, undeclared: {', '.join(DEMO_EFFECTS)}",
        "model                                          held-out RMSE [mm]   max [mm]",
    ]
    for s in run.stages:
        label = STAGE_LABELS.get(s.name, f"+ {s.name}")
        lines.append(f"{label:47s} {s.rmse * 1e3:12.4f}   {float(s.holdout_errors.max()) * 1e3:9.4f}")
    lines.append(f"{'final model on the separate test file':47s} {test_rmse * 1e3:12.4f}")
    lines.append("effects found:" + ("" if run.effects_report else " none"))
    lines += ["  " + effect_line(e) for e in run.effects_report]
    return lines
