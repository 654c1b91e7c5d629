"""Output directories that never destroy what they did not write.

Every directory torchcal writes (a calibration run, a simulated campaign, the demo) carries a
marker file, :data:`MARKER`, holding the format and version. ``--out`` is replaced only when it
does not exist or is a directory with that marker (the outside contract: "replaced only when it is a
previous run directory of torchcal (or absent)"); anything else (any unmarked directory, even an
empty one, a file, the working directory or one of its parents, a directory holding an input file,
a parent that is a file, a place the user cannot write) is refused with an
:class:`~torchcal.errors.OptionError` *before* any work is done, touching nothing.

The marker lists every file and folder written (``files``); a marked directory that now holds anything
else (a user's notes, a folder, a symbolic link, a FIFO) is refused naming those entries, so replacing it
deletes only what torchcal wrote. ``--out`` is resolved once (:func:`resolve_out`: ``RUN/robot/..`` is
``RUN``), and the checks and the final ``rename`` act on that one path.

Output *files* (``predict``, ``compensate``, ``convert``) start with the line :data:`FILE_MARKER`; an existing
file without it is replaced only with ``--force`` (:func:`check_out_file`).

Writing happens in a temporary directory beside ``--out`` (``.NAME.XXXX.tmp``, marked first) while
``.NAME.lock`` is locked with ``fcntl.flock``; the temporary then replaces ``--out`` by ``rename``.
Temporaries of killed runs (``.NAME.*.tmp`` / ``.NAME.*.old`` that carry the marker) are removed by
the next run that takes the lock: while it holds the lock no other writer can own them.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import secrets
import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path

from torchcal.errors import OptionError

#: The marker file of a torchcal output directory.
MARKER = ".torchcal-run"
#: What the marker holds; ``format`` identifies it, ``version`` the layout.
MARKER_FORMAT = "torchcal-run"
MARKER_VERSION = 2  # 2: the marker lists the entries written ("files"); 1 did not
#: The first line of every output file torchcal writes (``# written_by: torchcal predict``): a comment line of
#: the measurement format (CONTRACT §1), so readers of the file take it as metadata.
FILE_MARKER = "# written_by: torchcal"
#: Most entries a marked directory may hold before it is refused unread (a run holds about twenty).
MAX_ENTRIES = 10_000


def _marker_text(kind: str, files: list[str] | None = None) -> str:
    doc = {"format": MARKER_FORMAT, "version": MARKER_VERSION, "written_by": kind}
    if files is not None:
        doc["files"] = files
    return json.dumps(doc) + "\n"


def _read_marker(marker: Path) -> dict | None:
    """The marker's JSON object, or None when it is not a readable, well-formed marker (bounded, never blocks)."""
    from torchcal._inputs import load_json

    class _Bad(Exception):
        pass

    try:
        doc = load_json(marker, "marker", _Bad)
    except _Bad:
        return None
    return doc if isinstance(doc, dict) and doc.get("format") == MARKER_FORMAT else None


def resolve_out(out: str | os.PathLike) -> Path:
    """The one path ``--out`` names, resolved before any check (every check and the final rename use it).

    The parent is resolved through symbolic links and ``..``; the last component is kept as given, so a
    symbolic link given as ``--out`` stays a link (and is refused), never followed. A last component of
    ``.`` or ``..`` (``RUN/robot/..``) names a directory reached by walking: it is resolved whole.
    """
    p = Path(out)
    if p.name in ("", ".", ".."):
        return Path(os.path.realpath(p))
    return Path(os.path.realpath(p.parent)) / p.name


#: What a calibration run directory held before the marker existed (torchcal 0.1 before this module).
_LEGACY_RUN_FILES = {
    "report.json",
    "report.md",
    "robot_calibrated.urdf",
    "model.pt",
    "model.json",
    "robot",
    "covariance.pt",
}


def _is_legacy_run(path: Path) -> bool:
    """An unmarked run directory of an earlier torchcal: its model.json format, and nothing else in it."""
    from torchcal._inputs import load_json

    class _Bad(Exception):
        pass

    try:
        names = {p.name for p in path.iterdir()}
        meta = load_json(path / "model.json", "model.json", _Bad)  # a FIFO or /dev/zero is not a run
    except (OSError, _Bad):
        return False
    extra = {n for n in names - _LEGACY_RUN_FILES if not n.endswith(".png")}
    return (
        isinstance(meta, dict)
        and meta.get("format") == "torchcal-run-1"
        and not extra
        and not any((path / n).is_symlink() for n in names)
    )


def _is_legacy_demo(path: Path) -> bool:
    """An unmarked ``torchcal demo`` output of an earlier torchcal: data/, run/ (a legacy run), summary.json."""
    try:
        names = {p.name for p in path.iterdir()}
    except OSError:
        return False
    return (
        names == {"data", "run", "summary.json"}
        and _is_legacy_run(path / "run")
        and {p.name for p in (path / "data").iterdir()} <= {"train.csv", "test.csv", "truth.json"}
    )


def is_marked(path: Path) -> bool:
    """Whether ``path`` is a directory carrying a readable torchcal marker (or is an unmarked run
    directory or demo output of an earlier torchcal holding nothing but its own files)."""
    marker = path / MARKER
    if path.is_symlink() or not path.is_dir():
        return False
    if not marker.exists() and (_is_legacy_run(path) or _is_legacy_demo(path)):
        return True
    if marker.is_symlink() or not marker.is_file():
        return False
    return _read_marker(marker) is not None


#: What each kind of output held before its marker listed its files (marker version 1 and unmarked outputs of an
#: earlier torchcal): patterns of relative paths, folders ending in '/'.
_LEGACY_ENTRIES = {
    "calibrate": ("report.json", "report.md", "*.png", "robot_calibrated.urdf", "model.pt", "model.json", "robot/")
    + ("robot/*", "covariance.pt"),
    "simulate": ("train.csv", "test.csv", "truth.json"),
    "demo": ("summary.json", "data/", "data/train.csv", "data/test.csv", "data/truth.json", "run/", f"run/{MARKER}")
    + ("run/report.json", "run/report.md", "run/*.png", "run/robot_calibrated.urdf", "run/model.pt")
    + ("run/model.json", "run/robot/", "run/robot/*", "run/covariance.pt"),
}


def foreign_entries(path: Path) -> list[str]:
    """The entries of the torchcal output directory ``path`` that torchcal did not write, as relative paths.

    What torchcal wrote is the marker's ``files`` list (or, for a marker without one and for an unmarked
    output of an earlier torchcal, :data:`_LEGACY_ENTRIES` of its kind). Symbolic links, FIFOs, devices and
    sockets are never torchcal's; a folder torchcal did not write is named, not entered.
    """
    import fnmatch

    doc = _read_marker(path / MARKER) if (path / MARKER).is_file() else None
    if doc is None:  # an unmarked output of an earlier torchcal (is_marked said so)
        doc = {"written_by": "demo" if (path / "summary.json").exists() else "calibrate"}
    files = doc.get("files")
    if isinstance(files, list) and all(isinstance(f, str) for f in files):
        listed = set(files)

        def ours(rel: str) -> bool:
            return rel in listed

    else:
        patterns = _LEGACY_ENTRIES.get(str(doc.get("written_by")), ())

        def ours(rel: str) -> bool:
            return any(fnmatch.fnmatchcase(rel, pat) and pat.count("/") == rel.count("/") for pat in patterns)

    foreign: list[str] = []
    seen = 0
    stack = [("", path)]
    while stack:
        prefix, d = stack.pop()
        try:
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError as e:
            raise OptionError(f"{d}: cannot be read: {e.strerror or e}") from None
        for e in entries:
            seen += 1
            if seen > MAX_ENTRIES:
                return foreign + [f"(more than {MAX_ENTRIES} entries)"]
            rel = prefix + e.name
            if rel == MARKER:
                continue
            if e.is_symlink():
                foreign.append(f"{rel} (a symbolic link)")
            elif e.is_dir(follow_symlinks=False):
                if ours(rel + "/"):
                    stack.append((rel + "/", Path(e.path)))
                else:
                    foreign.append(rel + "/")
            elif not e.is_file(follow_symlinks=False):
                foreign.append(f"{rel} (not a regular file)")
            elif not ours(rel):
                foreign.append(rel)
    return sorted(foreign)


def _listing(root: Path) -> list[str]:
    """Every entry under ``root`` (not the top marker) as a relative path, folders ending in '/'."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel = Path(dirpath).relative_to(root)
        prefix = "" if str(rel) == "." else rel.as_posix() + "/"
        out += [prefix + d + "/" for d in dirnames]
        out += [prefix + f for f in filenames if prefix + f != MARKER]
    return sorted(out)


def _write_listings(root: Path) -> None:
    """Rewrite the marker of ``root`` and of every marked folder below it with the list of what it holds."""
    for dirpath, _, filenames in os.walk(root):
        if MARKER in filenames:
            d = Path(dirpath)
            doc = _read_marker(d / MARKER) or {}
            (d / MARKER).write_text(_marker_text(str(doc.get("written_by", "?")), _listing(d)), encoding="utf-8")


def _within(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def _probe_writable(parent: Path, where: str) -> None:
    """Create and remove a directory in ``parent``: ``os.access`` says yes to root and on read-only mounts."""
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OptionError(f"{where}: cannot write in {parent} (permission denied)")
    probe = parent / f".torchcal-probe.{secrets.token_hex(4)}"
    try:
        os.mkdir(probe)
    except OSError as e:
        raise OptionError(f"{where}: cannot write in {parent} ({e.strerror or e})") from None
    with contextlib.suppress(OSError):
        os.rmdir(probe)


def check_out_dir(out: str | os.PathLike, *, inputs: Sequence[str | os.PathLike] = (), option: str = "--out") -> Path:
    """Refuse an output directory that may not be replaced; return it as a :class:`Path`.

    Args:
        out: the directory to write.
        inputs: files the command reads; ``out`` must not contain any of them.
        option: the option's name, for the messages.

    Returns:
        ``out`` resolved (:func:`resolve_out`): the path to write.

    Raises:
        OptionError: ``out`` holds something torchcal did not write, contains an input, is the
            working directory or above it, or its nearest existing parent is not a writable directory.
    """
    where = f"{option} {out}"
    out = resolve_out(out)
    absolute = out
    real = Path(os.path.realpath(out))
    if absolute.parent == absolute or real.parent == real:
        raise OptionError(f"{where}: a filesystem root cannot be a run directory; name a new directory")
    cwd = Path(os.path.realpath(os.getcwd()))
    if _within(cwd, real):
        raise OptionError(
            f"{where}: is the working directory or one of its parents; name a new directory (e.g. runs/cal)"
        )
    for f in inputs:
        if f is None:
            continue
        fr = Path(os.path.realpath(f))
        if _within(fr, real):
            raise OptionError(
                f"{where}: contains the input {f}; replacing it would delete the input. Name a new directory"
            )
    if out.is_symlink():
        raise OptionError(f"{where}: is a symbolic link; torchcal replaces only directories it wrote")
    if out.exists():
        if not out.is_dir():
            raise OptionError(
                f"{where}: exists and is not a directory; torchcal will not replace it. Name a new directory"
            )
        if not is_marked(out):
            try:
                empty = not any(out.iterdir())
            except OSError as e:
                raise OptionError(f"{where}: cannot be read: {e.strerror or e}") from None
            what = "is an empty directory" if empty else "exists, is not empty"
            raise OptionError(
                f"{where}: {what} and is not a torchcal output directory (no {MARKER} "
                "marker); torchcal replaces only its own run directories. Name a new directory "
                + ("or remove this empty one (rmdir)" if empty else "or remove this one yourself")
            )
        foreign = foreign_entries(out)
        if foreign:
            shown = ", ".join(foreign[:10]) + (f" and {len(foreign) - 10} more" if len(foreign) > 10 else "")
            raise OptionError(
                f"{where}: is a torchcal output directory but holds what torchcal did not write: {shown}; "
                "replacing it would delete them. Move them out or name a new directory"
            )
    _check_creatable(absolute, where)
    return out


def _check_creatable(absolute: Path, where: str) -> None:
    """Refuse ``absolute`` unless its nearest existing ancestor is a directory we may create entries in."""
    parent = absolute.parent
    while not parent.exists() and not parent.is_symlink():
        parent = parent.parent
    if not parent.is_dir():
        raise OptionError(f"{where}: {parent} is not a directory, so nothing can be created below it")
    _probe_writable(parent, where)


def check_out_file(
    out: str | os.PathLike,
    *,
    inputs: Sequence[str | os.PathLike] = (),
    option: str = "--out",
    force: bool = False,
) -> Path:
    """Refuse an output file that is an input, a directory, a symbolic link, not a regular file, an existing
    file torchcal did not write (no :data:`FILE_MARKER` first line; ``force`` allows it), or under a parent
    that is not writable.

    Returns:
        ``out`` resolved (:func:`resolve_out`): the path to write (replaced atomically by the writer).
    """
    where = f"{option} {out}"
    target = resolve_out(out)
    if os.path.islink(target):
        raise OptionError(
            f"{where}: is a symbolic link; torchcal does not write through links. Name the file itself or a new one"
        )
    if target.is_dir():
        raise OptionError(f"{where}: is a directory; name the file to write")
    real = Path(os.path.realpath(target))
    for f in inputs:
        if f is None:
            continue
        fr = Path(os.path.realpath(f))
        if fr == real:
            raise OptionError(f"{where}: is the input file {f}; writing it would destroy the input. Name another file")
        if fr.is_dir() and _within(real, fr) and real.exists():
            raise OptionError(f"{where}: is a file of the input directory {f}; name a file outside it")
        if fr.is_dir() and _within(real, fr) and (fr / MARKER).is_file():
            # a run directory is written and replaced as a whole: a file added to it is lost with the next write
            raise OptionError(
                f"{where}: lies inside the run directory {f}, which torchcal replaces as a whole; "
                "write it beside the run"
            )
    if target.exists() and not target.is_file():
        raise OptionError(f"{where}: exists and is not a regular file")
    if target.exists() and not force and not written_by_torchcal(target):
        raise OptionError(
            f"{where}: exists and torchcal did not write it (its first line is not '{FILE_MARKER} ...'); "
            "pass --force to replace it, or name another file"
        )
    _check_creatable(target, where)
    return target


def written_by_torchcal(path: Path) -> bool:
    """Whether the regular file ``path`` starts with :data:`FILE_MARKER` (read without blocking, 256 bytes)."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        head = os.read(fd, 256)
    except OSError:
        return False
    finally:
        os.close(fd)
    return head.startswith(FILE_MARKER.encode() + b" ")


@contextlib.contextmanager
def _locked(lock_path: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``lock_path``; the file is removed on release.

    Removing a lock file is safe only when every holder checks, after locking, that the path still
    names the inode it locked (otherwise a waiter could lock a removed file while a newcomer locks a
    new one): hence the loop.
    """
    while True:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                same = os.fstat(fd).st_ino == os.stat(lock_path).st_ino
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock_path)
        os.close(fd)


def _clean_stale(parent: Path, name: str) -> None:
    """Remove marked temporaries of earlier killed runs for ``name`` (the caller holds the lock).

    Only names this module makes for ``name`` (``.NAME.<8 hex>.tmp|old``; and ``.NAME.<8 chars>`` /
    ``.NAME.old`` of the writer before it): the temporaries of ``NAME.x`` are not ours to remove.
    """
    pattern = re.compile(rf"\.{re.escape(name)}\.(?:[0-9a-f]{{8}}\.(?:tmp|old)|[a-z0-9_]{{8}}|old)")
    try:
        entries = list(parent.iterdir())
    except OSError:
        return
    for p in entries:
        if pattern.fullmatch(p.name) and not p.is_symlink() and is_marked(p):
            shutil.rmtree(p, ignore_errors=True)


def _make_temp_dir(parent: Path, name: str) -> Path:
    """A new ``.NAME.XXXXXXXX.tmp`` directory; unlike ``mkdtemp`` its mode follows the umask like ``mkdir``."""
    for _ in range(100):
        tmp = parent / f".{name}.{secrets.token_hex(4)}.tmp"
        try:
            os.mkdir(tmp)
        except FileExistsError:
            continue
        return tmp
    raise OptionError(f"cannot create a temporary directory in {parent}")  # pragma: no cover


@contextlib.contextmanager
def replace_dir(out: str | os.PathLike, *, kind: str, inputs: Sequence[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a fresh marked temporary directory that replaces ``out`` when the block succeeds.

    Args:
        out: the output directory (checked again with :func:`check_out_dir` under the lock).
        kind: the command that writes it, recorded in the marker.
        inputs: files that ``out`` must not contain.

    On an exception the temporary is removed and ``out`` is left as it was.
    """
    given = out
    out = check_out_dir(given, inputs=inputs)  # resolved once: every later check and the rename act on it
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OptionError(f"--out {given}: cannot create {parent}: {e.strerror or e}") from None
    name = out.name
    with _locked(parent / f".{name}.lock"):
        _clean_stale(parent, name)
        check_out_dir(out, inputs=inputs)  # another writer may have changed it while we waited
        tmp = _make_temp_dir(parent, name)
        try:
            (tmp / MARKER).write_text(_marker_text(kind), encoding="utf-8")
            yield tmp
            _write_listings(tmp)  # the marker (and any nested one) lists what was written
            target = parent / name
            check_out_dir(out, inputs=inputs)  # still absent or ours: the block may have taken long
            if target.exists():
                old = Path(str(tmp)[: -len(".tmp")] + ".old")
                os.rename(target, old)
                os.rename(tmp, target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.rename(tmp, target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise


def mark(directory: str | os.PathLike, kind: str) -> None:
    """Write the marker into ``directory`` (a sub-directory that is itself a run, e.g. the demo's ``run/``)."""
    (Path(directory) / MARKER).write_text(_marker_text(kind), encoding="utf-8")
