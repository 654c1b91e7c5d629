"""A file written inside a run directory is lost when the run is written again (it is replaced as a whole): predict,
compensate and plan refuse such an --out before any work, as export does, and write nothing."""

import pytest

from torchcal.cli import main


@pytest.mark.parametrize("command", ["predict", "compensate", "plan"])
def test_an_out_inside_the_run_directory_is_refused(command, run_dir, campaign, capsys):
    out = run_dir / "sub" / f"{command}.csv"
    args = {
        "predict": ["predict", str(run_dir), str(campaign / "test.csv")],
        "compensate": ["compensate", str(run_dir), str(campaign / "test.csv")],
        "plan": ["plan", "--run", str(run_dir), "--n", "5", "--pool", "100"],
    }[command]
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "inside the run directory" in err and str(run_dir) in err
    assert not out.exists() and not out.parent.exists()
