"""Every fenced code block in README.md and docs/*.md runs, by its fence's language (the info string after the
opening backticks):

- ``python``: executed; the blocks of one file run in order in one namespace, in a fresh temporary directory.
- ``sh``: run with ``bash -e`` in a fresh temporary directory (the blocks of one file in order, in one shell), with
  this environment's ``torchcal`` first on PATH and this checkout first on PYTHONPATH.
- ``sh args-only``: commands that take minutes to hours (benchmarks, the paper's experiments, the real-data study,
  ``make test`` itself) or need data that are not in the repository. They are not run; every command is checked:
  ``python scripts/NAME.py ARGS`` -- the script exists and its module-level argparse parser accepts exactly ARGS;
  ``torchcal ARGS`` -- the command's parser accepts them; ``make TARGET`` -- the Makefile has the target
  (``make -n``); ``pytest PATH`` -- the path exists. Leading ``VAR=value`` assignments are allowed. Any other
  command in such a block fails the test.
- ``text``, ``json``, ``yaml``: output or file contents, not run.

A fence without a language, or with one not listed here, fails the test.
"""

import argparse
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUN = {"python", "sh"}
CHECK = {"sh args-only"}
NOT_RUN = {"text", "json", "yaml"}
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", flags=re.S | re.M)


def blocks(path: Path) -> list[tuple[str, str, int]]:
    """(info string, body, 1-based line of the opening fence) of every fenced block in ``path``."""
    text = path.read_text(encoding="utf-8")
    return [(m.group(1).strip(), m.group(2), text.count("\n", 0, m.start()) + 1) for m in FENCE.finditer(text)]


def _id(path: Path) -> str:
    return str(path.relative_to(ROOT))


def test_the_pages_have_blocks_and_the_readme_is_short():
    assert len(FILES) > 5, "docs/ pages are missing"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 300
    langs = [lang for lang, _, _ in blocks(ROOT / "README.md")]
    assert langs.count("python") >= 1 and langs.count("sh") >= 1
    for f in FILES[1:]:
        assert f"docs/{f.name}" in readme or f"({f.name})" in (ROOT / "docs" / "README.md").read_text(), (
            f"{f.name} is linked from neither README.md nor docs/README.md"
        )


@pytest.mark.parametrize("path", FILES, ids=_id)
def test_relative_links_and_images_exist(path):
    text = path.read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if not re.match(r"[a-z]+:", target):
            assert (path.parent / target).exists(), f"{path.name}: the link {target!r} points nowhere"


@pytest.mark.parametrize("path", FILES, ids=_id)
def test_every_block_has_a_known_language(path):
    text = path.read_text(encoding="utf-8")
    assert text.count("```") % 2 == 0, f"{path.name}: an unclosed fence"
    for lang, _, line in blocks(path):
        assert lang, f"{path.name}:{line}: a fenced block without a language"
        assert lang in RUN | CHECK | NOT_RUN, f"{path.name}:{line}: unknown fence language {lang!r}"


@pytest.mark.slow
@pytest.mark.parametrize("path", [f for f in FILES if any(lg == "python" for lg, _, _ in blocks(f))], ids=_id)
def test_python_blocks_run(path, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__readme__"}
    for lang, body, line in blocks(path):
        if lang == "python":
            exec(compile("\n" * line + body, str(path), "exec"), namespace)
    out = capsys.readouterr().out
    if path.name == "README.md":  # what the comments next to the prints say
        assert "['compliance']" in out and "'converged': 50" in out
        assert "torch.Size([10, 4, 4]) torch.Size([10, 3])" in out


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


@pytest.mark.slow
@pytest.mark.parametrize("path", [f for f in FILES if any(lg == "sh" for lg, _, _ in blocks(f))], ids=_id)
def test_shell_blocks_run(path, tmp_path):
    assert shutil.which("torchcal", path=str(Path(sys.executable).parent)), "torchcal is not installed beside python"
    script = "\n".join(body for lang, body, _ in blocks(path) if lang == "sh")
    done = subprocess.run(
        ["bash", "-e", "-o", "pipefail", "-c", script],
        cwd=tmp_path,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, f"{path.name}: exit {done.returncode}\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}"
    if path.name == "README.md":
        assert done.stdout.strip() == "50"  # every test point reached (grep -c converged)


def _commands(body: str) -> list[list[str]]:
    """The commands of a block: continuation lines joined, comments and VAR=value prefixes dropped."""
    out = []
    for line in body.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
            words.pop(0)
        if words:
            out.append(words)
    return out


class _Refused(Exception):
    pass


def _parse(parser: argparse.ArgumentParser, args: list[str], what: str) -> None:
    """``parser`` accepts exactly ``args`` (no unknown flag, every value of the right type and choice)."""

    def refuse(message):
        raise _Refused(f"{what}: {message}")

    parsers = [parser]
    for action in parser._actions:  # subcommands report their errors through their own parser
        if isinstance(action, argparse._SubParsersAction):
            parsers += list(action.choices.values())
    saved = [p.error for p in parsers]
    for p in parsers:
        p.error = refuse
    try:
        parser.parse_args(args)
    except SystemExit as e:  # --help, or an action that exits
        raise _Refused(f"{what}: exits ({e.code}) while parsing") from None
    finally:
        for p, error in zip(parsers, saved, strict=True):
            p.error = error


_SCRIPT_PARSERS: dict[str, argparse.ArgumentParser] = {}


def _script_parser(script: Path) -> argparse.ArgumentParser:
    if str(script) not in _SCRIPT_PARSERS:
        found = [v for v in runpy.run_path(str(script), run_name="__doc_check__").values()]
        parsers = [v for v in found if isinstance(v, argparse.ArgumentParser)]
        assert len(parsers) == 1, f"{script.name}: no single module-level argparse parser to check against"
        _SCRIPT_PARSERS[str(script)] = parsers[0]
    return _SCRIPT_PARSERS[str(script)]


def _check(words: list[str], where: str) -> None:
    head, args = words[0], words[1:]
    if head in ("python", "python3"):
        assert args and args[0].startswith("scripts/"), f"{where}: only `python scripts/NAME.py ...` is checked"
        script = ROOT / args[0]
        assert script.is_file(), f"{where}: {args[0]} does not exist"
        _parse(_script_parser(script), args[1:], f"{where}: {args[0]}")
    elif head == "torchcal":
        import torchcal.cli

        _parse(torchcal.cli.build_parser(), args, f"{where}: torchcal")
    elif head == "make":
        assert len(args) == 1, f"{where}: make takes one target here"
        done = subprocess.run(["make", "-n", "-C", str(ROOT), args[0]], capture_output=True, text=True)
        assert done.returncode == 0, f"{where}: the Makefile has no target {args[0]!r}: {done.stderr}"
    elif head == "pytest":
        assert args and all((ROOT / a.split("::")[0]).exists() for a in args if not a.startswith("-")), where
    else:
        raise AssertionError(f"{where}: {head!r} cannot be checked in an args-only block (see this file's docstring)")


_CHECKED = [f for f in FILES if any(lg in CHECK for lg, _, _ in blocks(f))]


@pytest.mark.parametrize("path", _CHECKED, ids=_id)
def test_args_only_blocks_name_real_scripts_and_flags(path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.chdir(ROOT)
    n = 0
    for lang, body, line in blocks(path):
        if lang in CHECK:
            commands = _commands(body)
            assert commands, f"{path.name}:{line}: an empty args-only block"
            for words in commands:
                try:
                    _check(words, f"{path.name}:{line}")
                except _Refused as e:
                    raise AssertionError(str(e)) from None
                n += 1
    assert n


def test_args_only_check_refuses_a_wrong_flag():
    """The check is not vacuous: an unknown flag, a wrong choice and a missing script fail."""
    for words in (
        ["python", "scripts/bench_ekf.py", "--no-such-flag"],
        ["torchcal", "calibrate", "x.csv", "--robot", "ur5", "--out", "o", "--engine", "nonsense"],
        ["torchcal", "calibrate", "x.csv", "--robot", "ur5"],
    ):
        with pytest.raises(_Refused):
            _check(words, "self-test")
    with pytest.raises(AssertionError, match="does not exist"):
        _check(["python", "scripts/no_such_script.py"], "self-test")
    with pytest.raises(AssertionError, match="cannot be checked"):
        _check(["rm", "-rf", "runs"], "self-test")
