"""The command's entry point ends the process itself (torchcal._entry): what a normal exit guarantees must hold."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# buffered output before the command (stdout is a pipe: block-buffered), an atexit handler, and a command that
# refuses its input: the exit code, the refusal, the buffered line and the handler's line must all come out
SCRIPT = """
import atexit, sys
from torchcal import _entry
print("before the command")
atexit.register(lambda: print("atexit handler ran"))
sys.argv = ["torchcal", "calibrate", "no-such-file.csv", "--robot", "ur5", "--out", "o"]
_entry.main()
print("never reached: the entry point ends the process")
"""


def test_the_command_ends_the_process_with_its_code_streams_flushed_and_atexit_run(tmp_path):
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "no-such-file.csv" in r.stderr and "no such file" in r.stderr
    assert r.stdout.splitlines() == ["before the command", "atexit handler ran"], r.stdout
    assert not (tmp_path / "o").exists()


def test_called_with_argv_it_returns_the_code(tmp_path):
    argv = "['calibrate', 'no-such-file.csv', '--robot', 'ur5', '--out', 'o']"
    code = f"from torchcal import _entry; print(_entry.main({argv}))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.strip() == "2", (r.stdout, r.stderr)


def test_the_command_line_loads_without_torch():
    """``torchcal --help`` and every command's parser need no torch (1.5-2.5 s of CPU to import): each handler
    imports what it computes with."""
    code = "import sys, torchcal.cli; torchcal.cli.build_parser(); print('torch' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0 and r.stdout.strip() == "False", (r.stdout, r.stderr)
