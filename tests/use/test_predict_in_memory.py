"""The library's documented API (issue 48 item 6): ``run.model.predict(q)`` in memory gives what ``predict`` gives
from the run directory; ``set_verbosity`` silences the stages; a device this build lacks is a clear error."""

import pytest
import torch

import torchcal
from tests._cli import _golden


@pytest.mark.slow
def test_predict_in_memory_equals_predict_from_the_run_directory(tmp_path):
    from torchcal.report import write_run
    from torchcal.use import predict

    run = _golden().golden_run("auto")
    test = _golden().campaign().test
    write_run(run, tmp_path / "run")
    torch.testing.assert_close(run.model.predict(test.q), predict(tmp_path / "run", test), rtol=0, atol=1e-12)


def test_set_verbosity_quiet_silences_the_stage_messages(capsys):
    from torchcal import _console

    before = torchcal.set_verbosity("quiet")
    try:
        _console.info("a stage")
        assert capsys.readouterr().err == ""
        assert torchcal.set_verbosity("info") == "quiet"
        _console.info("a stage")
        assert capsys.readouterr().err == "a stage\n"
    finally:
        torchcal.set_verbosity(before)
    with pytest.raises(torchcal.OptionError, match="'loud' is not one of info, quiet"):
        torchcal.set_verbosity("loud")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this torch has CUDA: the device exists")
def test_load_robot_on_a_missing_cuda_device_names_the_argument():
    with pytest.raises(torchcal.OptionError, match=r"no CUDA device is available.*use device 'cpu'"):
        torchcal.load_robot("ur5", device="cuda")
