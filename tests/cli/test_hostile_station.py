"""Issue 35, items 9 and 11 (the ``station`` parts): a station of one to three rows, ``--probe`` on a run of one
probe, and points of another robot given to ``station``: refused with exit 2, the file and the cause, nothing
written."""

import json
from dataclasses import replace

import torch
from _cli import calibrate, cli_simulate

from torchcal.cli import main
from torchcal.data import read_measurements, write_measurements


def _relabel(src, dst, rows: int):
    """``src`` with its first ``rows`` rows moved to a third station S3."""
    m = read_measurements(src)
    st = m.station.clone()
    st[:rows] = 2
    write_measurements(dst, replace(m, station=st, station_names=(*m.station_names, "S3")))


def test_a_station_of_too_few_poses_is_refused_naming_file_and_station(tmp_path, capsys):
    assert cli_simulate(tmp_path / "sim", "--poses", "80", "--test-poses", "10", "--seed", "4", "--stations", "2",
                        "--probes", "2") == 0  # fmt: skip
    train = tmp_path / "sim" / "train.csv"
    for rows in (1, 3):  # 1 row; 3 rows at 2 poses (a nest's two probes measured at one pose count once)
        _relabel(train, tmp_path / f"few{rows}.csv", rows)
        capsys.readouterr()
        assert calibrate(tmp_path / f"few{rows}.csv", tmp_path / f"out{rows}") == 2
        err = capsys.readouterr().err
        assert f"few{rows}.csv" in err and "station 'S3'" in err and "at least 3 poses" in err, err
        assert not (tmp_path / f"out{rows}").exists()
    # 6 rows at 3 poses: calibrated; the station keeps them all for its pose (none held out) instead of losing them
    _relabel(train, tmp_path / "few6.csv", 6)
    assert calibrate(tmp_path / "few6.csv", tmp_path / "out6") == 0
    s3 = json.loads((tmp_path / "out6" / "report.json").read_text())["stations"]["S3"]
    assert s3["n_train"] == 6 and s3["n_holdout"] == 0


def test_station_refuses_probe_on_a_one_probe_run_and_points_of_another_robot(run_dir, campaign, tmp_path, capsys):
    pts = read_measurements(campaign / "test.csv")
    write_measurements(tmp_path / "pts.csv", pts.subset(torch.arange(6)))
    out = tmp_path / "r"
    assert main(["station", str(run_dir), str(tmp_path / "pts.csv"), "--out", str(out), "--probe", "P1"]) == 2
    assert "single probe" in capsys.readouterr().err and not out.exists()
    # UR10 points (no '# robot:' line to tell) on the UR5 run: chi-square 6.6e8 and a warning before; now stopped
    assert cli_simulate(tmp_path / "ur10", "--poses", "20", "--test-poses", "6", "--seed", "2", robot="ur10") == 0
    other = read_measurements(tmp_path / "ur10" / "test.csv")
    write_measurements(tmp_path / "other.csv", replace(other, meta={}))
    capsys.readouterr()
    assert main(["station", str(run_dir), str(tmp_path / "other.csv"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "other.csv" in err and "another robot" in err and not out.exists()
    assert main(["station", str(run_dir), str(tmp_path / "pts.csv"), "--out", str(out), "--quiet"]) == 0  # as ever
