"""Reading input files without hanging and without reading without end.

Every file torchcal reads from the user (a measurement CSV, a robot description, a run directory's
``model.json`` and ``model.pt``, the ``.torchcal-run`` marker) goes through :func:`read_bounded`: a FIFO,
a device (``/dev/zero``), a socket or a directory is refused *before* it is opened for reading (opening a
FIFO with no writer blocks; reading ``/dev/zero`` never ends), and a regular file larger than its kind
can be is refused before it is read. The limits are generous for real files, small enough that the worst
input costs a bounded amount of memory. :func:`check_nesting` bounds the depth of JSON and YAML documents
the same way, before a recursive parser sees them.
"""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Callable

MiB = 1024 * 1024
#: Largest files accepted, by kind [bytes]: real files are far smaller (a 100,000-pose CSV is about 15 MiB).
LIMITS = {
    "measurement file": 256 * MiB,
    "robot description": 8 * MiB,
    "model.json": 16 * MiB,
    "report.json": 64 * MiB,
    "model.pt": 1024 * MiB,
    "covariance.pt": 64 * MiB,
    "geometric.pt": 64 * MiB,
    "covariance_geometric.pt": 64 * MiB,
    "standalone.pt": 64 * MiB,
    "nominal.pt": 64 * MiB,
    "covariance_nominal.pt": 64 * MiB,
    "covariance_beyond.pt": 64 * MiB,
    "holdout.pt": 256 * MiB,
    "marker": 1 * MiB,
    "fleet manifest": 16 * MiB,
    "MAP": 1 * MiB,
    "convert input": 256 * MiB,
}
#: Deepest nesting of lists and mappings accepted in a JSON or YAML input: real files nest a handful of levels.
MAX_DEPTH = 64


def kind_of(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISDIR, "a directory"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str | os.PathLike, kind: str, error: Callable[[str], Exception]) -> os.stat_result:
    """The ``os.stat`` of ``path`` if it is a regular file (links followed); the one check every input path takes.

    Never opens the path: opening a FIFO with no writer blocks, and a device reads without end.

    Raises:
        Whatever ``error`` builds from a message that does not name the file: no such file, a directory, a FIFO,
        a device, a socket, or a path that cannot be looked at.
    """
    try:
        st = os.stat(path)  # stat never blocks, unlike opening a FIFO
    except FileNotFoundError:
        raise error(f"no such file (the {kind})") from None
    except OSError as e:
        raise error(f"cannot read the file: {e.strerror or e}") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"is {kind_of(st.st_mode)}, not a regular file; give a {kind} saved as a file")
    return st


def read_text_bounded(path: str | os.PathLike, kind: str, error: Callable[[str], Exception]) -> str:
    """The UTF-8 text (a byte-order mark dropped) of the regular file ``path``, read with :func:`read_bounded`."""
    raw = read_bounded(path, kind, error)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"is not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start})") from None


def read_bounded(
    path: str | os.PathLike, kind: str, error: Callable[[str], Exception], *, limit: int | None = None
) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` (default ``LIMITS[kind]``) of them.

    Args:
        path: the file (symbolic links are followed: a link to a regular file is a regular file).
        kind: a key of :data:`LIMITS`, named in the messages.
        error: builds the exception to raise from a message that does not name the file (the caller's
            error names it, e.g. ``lambda m: MeasurementFileError(path, m)``).

    Raises:
        Whatever ``error`` builds: the path is not a regular file, is larger than the limit, or cannot be read.
    """
    limit = LIMITS[kind] if limit is None else limit
    st = check_regular(path, kind, error)
    if st.st_size > limit:
        raise error(f"{st.st_size} bytes is larger than a {kind} can be (at most {_size(limit)})")
    try:
        # O_NONBLOCK: should the path have been swapped for a FIFO since the stat, opening it does not block
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        raise error(f"cannot read the file: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"is {kind_of(st.st_mode)}, not a regular file; give a {kind} saved as a file")
        chunks, total = [], 0
        while total <= limit:
            chunk = os.read(fd, min(8 * MiB, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as e:
        raise error(f"cannot read the file: {e.strerror or e}") from None
    finally:
        os.close(fd)
    if total > limit:  # it grew while we read it
        raise error(f"is larger than a {kind} can be (at most {_size(limit)})")
    return b"".join(chunks)


def _size(n: int) -> str:
    return f"{n // MiB} MiB" if n >= MiB else f"{n} bytes"


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
_OPEN, _CLOSE = frozenset("[{"), frozenset("]}")


def check_nesting(text: str, error: Callable[[str], Exception]) -> None:
    """Refuse a JSON text nested deeper than :data:`MAX_DEPTH` lists and objects.

    ``json`` recurses per level and fails with a ``RecursionError`` on 200,000 nested ``[``; this linear
    scan (strings skipped) stops at the first bracket too deep. (YAML is bounded on its event stream, which
    PyYAML produces without recursion: :func:`torchcal.robot.load.load_dh_yaml`.)
    """
    text = _JSON_STRING.sub("", text)
    depth = 0
    for m in re.finditer(r"[\[\]{}]", text):
        if m.group() in _OPEN:
            depth += 1
            if depth > MAX_DEPTH:
                raise error(f"nested more than {MAX_DEPTH} levels deep; refused")
        else:
            depth = max(depth - 1, 0)


def load_json(path: str | os.PathLike, kind: str, error: Callable[[str], Exception]):
    """The JSON document of the file ``path``, read with :func:`read_bounded` and :func:`check_nesting`.

    Strict: ``NaN``, ``Infinity`` and numbers beyond float range (``1e400``) are refused, as are duplicate keys
    in an object; ``error`` builds the exception from a message (see :func:`read_bounded`).
    """
    import json
    import math

    raw = read_bounded(path, kind, error)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"is not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start})") from None
    check_nesting(text, error)

    def constant(name: str):
        raise ValueError(f"{name} is not a JSON number")

    def number(text: str) -> float:
        v = float(text)
        if not math.isfinite(v):
            raise ValueError(f"{text} is beyond the range of a float")
        return v

    def pairs(items: list) -> dict:
        out = {}
        for k, v in items:
            if k in out:
                raise ValueError(f"key {k!r} appears twice in one object")
            out[k] = v
        return out

    try:
        return json.loads(text, parse_constant=constant, parse_float=number, object_pairs_hook=pairs)
    except (ValueError, RecursionError) as e:
        raise error(f"cannot be read as JSON: {e}") from None
