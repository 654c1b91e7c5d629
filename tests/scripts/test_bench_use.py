"""The agreement check and the cases of ``scripts/bench_use.py`` (the timings themselves are measured, not tested)."""

from experiments.bench_use import agreement, cases


def _csv(path, rows):
    path.write_text("# written_by: torchcal predict\n" + "\n".join(",".join(r) for r in rows) + "\n")
    return path


def test_outputs_agree_to_1e12_relative_or_a_picometre(tmp_path):
    a = _csv(tmp_path / "a.csv", [["x", "miss", "status"], ["1.0", "2e-12", "converged"]])
    same = _csv(tmp_path / "b.csv", [["x", "miss", "status"], ["1.0000000000005", "2.9e-12", "converged"]])
    assert agreement(a, same)["agree"]
    moved = _csv(tmp_path / "c.csv", [["x", "miss", "status"], ["1.00000000001", "2e-12", "converged"]])
    out = agreement(a, moved)
    assert not out["agree"] and out["column"] == "x" and 5e-12 < out["max_relative"] < 2e-11
    text = _csv(tmp_path / "d.csv", [["x", "miss", "status"], ["1.0", "2e-12", "limit"]])
    assert not agreement(a, text)["agree"]
    assert not agreement(a, _csv(tmp_path / "e.csv", [["x", "miss"], ["1.0", "2e-12"]]))["agree"]


def test_cases_follow_the_arguments():
    names = [c.name for c in cases("run", "data.csv", None, [100, 500], "ur5")]
    assert names == ["predict", "plan --n 100", "plan --n 500"]
    assert [c.name for c in cases(None, "data.csv", "t.csv", [], "ur5")] == []
