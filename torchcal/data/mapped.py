"""Import measurements in other layouts into the measurement format, as a MAP file describes them.

``torchcal convert --map MAP.yaml INPUT... --out DATA.csv``. The MAP is a small YAML mapping (docs/reference.md,
*Importing measurements*, has the full description and an example per layout)::

    read: {delimiter: whitespace, header: false}      # how every INPUT is read (text, YAML or .mat)
    units: {length: mm, angle: deg}                   # the inputs' units (default m, rad)
    joints: {input: 1, columns: 1-6, sign: [1, -1, 1, 1, 1, 1], offset: [0, 90, 0, 0, 0, 0]}
    position: {input: [2, 3], columns: 1-3}           # or matrix: (4x4 / 3x4 row-major), quaternion:
    probe: [A, B]                                      # one name per position input; or {column: ..}, {block: ..}
    extra: {temperature: Temp}                         # other columns, kept
    payload: Load                                      # kg; or [Load, X, Y, Z]: with its centre of mass (flange)
    torques: 8-14                                      # N m, one per joint: tau1..tauN

Columns are 1-based numbers, ranges ``"3-8"``, header names, or lists of them; a YAML row's list value ``q: [..]``
is the columns ``q[1]``, ``q[2]``, ... and the name ``q`` takes them all. A model joint is ``sign * reading +
offset`` (offset in the angle unit), in the order the columns are listed. Rows of separate joint and point files pair
by their order; ``joints: {input: [1, 2]}`` reads each points input's own joints. Every error names the file, line
and column; nothing is written before every row has been read.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchcal.data.ipa import matrix_to_rotvec
from torchcal.data.measurements import (
    Measurements,
    _valid_extra_name,
    _valid_label,
    labels_of,
    write_measurements,
)
from torchcal.errors import MeasurementFileError, OptionError

F64 = torch.float64
MAP_KEYS = (
    "read",
    "units",
    "joints",
    "position",
    "matrix",
    "quaternion",
    "extra",
    "station",
    "probe",
    "payload",
    "torques",
)
READ_KEYS = ("delimiter", "header", "comment", "decimal", "blocks", "rows", "variable")
#: how far a 4x4 pose's rotation may be from orthonormal, and a quaternion's norm from 1 (a pose printed to 6 digits)
ROTATION_TOLERANCE = 1e-5
LENGTH = {"m": 1.0, "mm": 1e-3}
ANGLE = {"rad": 1.0, "deg": math.pi / 180}


@dataclass
class Table:
    """One input read as rows of cells.

    Attributes:
        path: the file; header: column names (None: numbers only); rows: the cells, text or numbers;
        lines: the 1-based line (or row of a .mat array) of each row; blocks: a YAML row's block name, or None.
    """

    path: str
    header: list[str] | None
    rows: list[list]
    lines: list[int]
    blocks: list[str | None] = field(default_factory=list)


# ----------------------------------------------------------------------------------------------- the MAP file
def _yaml_loader():
    """A safe YAML loader whose mappings remember the line of each key (``where``) for error messages."""
    import yaml

    class Lined(dict):
        where: dict

    class Loader(yaml.SafeLoader):
        pass

    def mapping(loader, node):
        seen = {}
        for k, _ in node.value:
            key = loader.construct_object(k)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                # PyYAML keeps the last of two equal keys: a second 'joints:' dropped the first's signs and offsets
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"key {key!r} appears twice (lines {seen[key]} and {k.start_mark.line + 1}); the second would "
                    "replace the first without a word: keep one",
                    k.start_mark,
                )
            if isinstance(key, (str, int, float, bool)):
                seen[key] = k.start_mark.line + 1
        out = Lined(loader.construct_mapping(node, deep=True))
        out.where = {loader.construct_object(k): k.start_mark.line + 1 for k, _ in node.value}
        out.where[None] = node.start_mark.line + 1
        return out

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    return Loader


#: the largest MAP: a MAP is a few lines; a bigger file is another file given as the MAP (the YAML parser would
#: take minutes over tens of MB before it failed)
MAX_MAP_BYTES = 1 << 20


def _load_yaml(path: str, what: str, max_bytes: int | None = None):
    import yaml

    from torchcal._inputs import check_regular, read_text_bounded

    # one check for every input path: a device, FIFO or directory refused unopened (/dev/zero read 2.2 GB)
    kind = "MAP" if what == "MAP" else "convert input"
    size = check_regular(path, kind, lambda m: MeasurementFileError(path, m)).st_size
    if max_bytes is not None and size > max_bytes:
        raise MeasurementFileError(
            path, f"{size} bytes; a {what} is a few lines (at most {max_bytes} bytes): is it the {what}?"
        )
    text = read_text_bounded(path, kind, lambda m: MeasurementFileError(path, m))
    try:
        return yaml.load(text, Loader=_yaml_loader())  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        raise MeasurementFileError(path, f"not valid YAML: {getattr(e, 'problem', e)}", line=line) from None


def _line(doc, key=None) -> int | None:
    return getattr(doc, "where", {}).get(key)


def read_map(path: str | os.PathLike) -> dict:
    """The MAP as a mapping, its keys checked (unknown ones name the MAP's line and list the valid ones)."""
    path = str(path)
    doc = _load_yaml(path, "MAP", MAX_MAP_BYTES)
    if not isinstance(doc, dict):
        raise MeasurementFileError(path, "a MAP is a YAML mapping with 'joints' and 'position', 'matrix' or ...")
    for key in doc:
        if key not in MAP_KEYS:
            raise MeasurementFileError(
                path, f"unknown key {key!r}; valid: {', '.join(MAP_KEYS)}", line=_line(doc, key), column=str(key)
            )
    if "joints" not in doc:
        raise MeasurementFileError(path, "the MAP needs 'joints' (the columns of the joint readings)")
    for key, valid in (("read", READ_KEYS), ("units", ("length", "angle"))):
        block = doc.get(key, {})
        if not isinstance(block, dict) or set(block) - set(valid):
            raise MeasurementFileError(path, f"'{key}' takes {', '.join(valid)}", line=_line(doc, key), column=key)
    for key, value in doc.get("read", {}).items():
        ok = isinstance(value, bool) or value == "auto" if key == "header" else isinstance(value, str) and value != ""
        if not ok or (key == "decimal" and value not in (".", ",")):
            raise MeasurementFileError(
                path,
                f"read.{key} = {value!r}: "
                + ("true, false or auto" if key == "header" else "a text")
                + (" ('.' or ',')" if key == "decimal" else ""),
                line=_line(doc["read"], key),
                column=key,
            )
    read = doc.get("read", {})
    if read.get("decimal") == "," and read.get("delimiter") == ",":
        raise MeasurementFileError(
            path, "read: a ',' delimiter with a ',' decimal mark cannot be told apart", line=_line(doc, "read")
        )
    units = doc.get("units", {})
    for key, table in (("length", LENGTH), ("angle", ANGLE)):
        if units.get(key, "m" if key == "length" else "rad") not in table:
            raise MeasurementFileError(
                path,
                f"units.{key} must be one of {', '.join(table)}, got {units[key]!r}",
                line=_line(units, key),
                column=key,
            )
    return doc


def _role(spec, map_path: str, doc: dict, key: str) -> dict:
    """A role (``joints``, ``position``, ...) as ``{"columns": ..., "input": [..], ...}`` (a bare spec is its
    columns; inputs are 1-based, default the first)."""
    role = dict(spec) if isinstance(spec, dict) else {"columns": spec}
    if "columns" not in role:
        raise MeasurementFileError(map_path, f"'{key}' needs 'columns'", line=_line(doc, key), column=key)
    given = role.get("input", 1)
    inputs = given if isinstance(given, list) else [given]
    if not inputs or not all(isinstance(i, int) and not isinstance(i, bool) and i >= 1 for i in inputs):
        raise MeasurementFileError(
            map_path, f"'{key}.input' must be input numbers from 1, got {given!r}", line=_line(doc, key), column=key
        )
    twice = next((i for k, i in enumerate(inputs) if i in inputs[:k]), None)
    if twice is not None:  # input: [2, 2] made two probes of identical rows, counted twice by the fit
        raise MeasurementFileError(
            map_path,
            f"'{key}.input' lists input {twice} twice ({given!r}): each input is read once",
            line=_line(doc, key),
            column=key,
        )
    role["input"] = inputs
    role["line"] = _line(doc, key)
    return role


# ------------------------------------------------------------------------------------------------- the inputs
def read_table(path: str, read: dict) -> Table:
    """An input as a :class:`Table`: ``.mat`` through scipy.io, ``.yaml``/``.yml`` as rows of mappings or lists,
    anything else as delimited text."""
    from torchcal._inputs import check_regular

    check_regular(path, "convert input", lambda m: MeasurementFileError(path, m))
    suffix = Path(path).suffix.lower()
    if suffix == ".mat":
        return _mat_table(path, read.get("variable"))
    if suffix in (".yaml", ".yml"):
        return _yaml_table(path, read)
    return _text_table(path, read)


def _mat_table(path: str, variable: str | None) -> Table:
    import numpy as np
    from scipy.io import loadmat

    try:
        content = loadmat(path)
    except Exception as e:  # scipy raises several types for a file that is not MATLAB's
        raise MeasurementFileError(path, f"not a MATLAB file scipy.io reads: {e}") from None
    arrays = {k: v for k, v in content.items() if not k.startswith("__") and isinstance(v, np.ndarray) and v.ndim == 2}
    if variable is None and len(arrays) != 1:
        raise MeasurementFileError(path, f"holds {len(arrays)} matrices ({', '.join(arrays)}); name one: read.variable")
    name = variable if variable is not None else next(iter(arrays))
    if name not in arrays or arrays[name].dtype.kind not in "fiu":
        raise MeasurementFileError(path, f"no numeric matrix named {name!r}; it has {', '.join(arrays) or 'none'}")
    rows = arrays[name].astype(float).tolist()
    return Table(path, None, rows, list(range(1, len(rows) + 1)), [None] * len(rows))


def _split(line: str, delimiter: str) -> list[str]:
    cells = line.split() if delimiter == "whitespace" else line.split(delimiter)
    return [c.strip() for c in cells]


def _delimiter(first: str, read: dict) -> str:
    given = read.get("delimiter", "auto")
    if given != "auto":
        return {"tab": "\t", "space": "whitespace"}.get(given, given)
    for d in ("\t", ";"):
        if d in first:
            return d
    return "," if "," in first and read.get("decimal", ".") != "," else "whitespace"


def _text_table(path: str, read: dict) -> Table:
    from torchcal._inputs import read_text_bounded

    text = read_text_bounded(path, "convert input", lambda m: MeasurementFileError(path, m))
    comment = tuple(read.get("comment", "#%"))
    body = [(k + 1, ln) for k, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith(comment)]
    if not body:
        raise MeasurementFileError(path, "no rows (blank and comment lines only)")
    delimiter = _delimiter(body[0][1], read)
    first = _split(body[0][1], delimiter)
    header = read.get("header", "auto")
    if header == "auto":
        header = any(_to_float(c, read) is None for c in first)
    names = first if header else None
    rows = body[1:] if header else body
    if not rows:
        raise MeasurementFileError(path, "a header and no rows")
    return Table(path, names, [_split(ln, delimiter) for _, ln in rows], [k for k, _ in rows], [None] * len(rows))


def _flatten(row) -> tuple[list, list[str] | None]:
    """A YAML row as cells and their names: a mapping's list values become ``key[1]``, ``key[2]``, ..."""
    if isinstance(row, list):
        return row, None
    cells, names = [], []
    for k, v in row.items():
        values = v if isinstance(v, list) else [v]
        cells += values
        names += [f"{k}[{i + 1}]" for i in range(len(values))] if isinstance(v, list) else [str(k)]
    return cells, names


def _yaml_blocks(path: str, doc, read: dict) -> list[tuple[str | None, object, int | None]]:
    """``(block name, its rows' list, line)`` per block (one unnamed block without ``read.blocks``)."""
    key_blocks, key_rows = read.get("blocks"), read.get("rows")
    if key_blocks is None:
        if key_rows is None or not isinstance(doc, dict):
            return [(None, doc, None)]
        return [(None, rows, line) for rows, line in _descend(doc, key_rows.split("."), _line(doc, key_rows))]
    blocks = doc.get(key_blocks) if isinstance(doc, dict) else None
    if isinstance(blocks, dict):  # name: block
        items = [(str(k), b, _line(blocks, k)) for k, b in blocks.items()]
    elif isinstance(blocks, list):
        items = [(None, b, _line(b)) for b in blocks]
    else:
        raise MeasurementFileError(path, f"expected a list or mapping of blocks under {key_blocks!r}")
    out = []
    for k, (name, block, line) in enumerate(items):
        if not isinstance(block, dict) and (key_rows is not None or name is None):
            raise MeasurementFileError(path, f"block {k + 1} is not a mapping (with its rows under 'rows')", line=line)
        name = name if name is not None else block.get("name", f"B{k + 1}")
        found = _descend(block, key_rows.split("."), line) if key_rows is not None else [(block, line)]
        out += [(name, rows, where) for rows, where in found]
    return out


def _descend(node, keys: list[str], line: int | None) -> list[tuple[object, int | None]]:
    """The rows' lists under the dotted path ``read.rows`` (``a.b``: key b of key a; ``*``: every entry of a mapping
    or list there): a YAML nested two levels (placements, column heights, then the stationing rows) reads as the
    placements' blocks, each with all its heights' rows. A missing key gives None (refused by the caller)."""
    if not keys:
        return [(node, line)]
    head, rest = keys[0], keys[1:]
    if head == "*" and isinstance(node, (dict, list)):
        entries = node.items() if isinstance(node, dict) else enumerate(node)
        return [found for k, v in entries for found in _descend(v, rest, _line(node, k) or line)]
    if not isinstance(node, dict) or head not in node:
        return [(None, line)]
    return _descend(node[head], rest, _line(node, head) or line)


def _yaml_table(path: str, read: dict) -> Table:
    doc = _load_yaml(path, "file")
    table = Table(path, None, [], [], [])
    for name, rows, line in _yaml_blocks(path, doc, read):
        if not isinstance(rows, list):
            raise MeasurementFileError(path, f"expected a list of rows under {read.get('rows')!r}", line=line)
        for row in rows:
            cells, names = _flatten(row if isinstance(row, (list, dict)) else [row])
            if table.header is None and names is not None:
                table.header = names
            if names is not None and names != table.header:
                raise MeasurementFileError(
                    path, f"this row's keys {names} differ from the first row's {table.header}", line=_line(row)
                )
            table.rows.append(cells)
            table.lines.append(_line(row) or line)
            table.blocks.append(name)
    if not table.rows:
        raise MeasurementFileError(path, "no rows")
    return table


# ------------------------------------------------------------------------------------------------ the columns
def _to_float(cell, read: dict) -> float | None:
    if isinstance(cell, bool):
        return None
    if isinstance(cell, (int, float)):
        return float(cell)
    text = str(cell).strip()
    if read.get("decimal", ".") == ",":
        text = text.replace(",", ".")
    if "_" in text or not text.isascii():
        return None  # float() reads '0_1' as 1 and Arabic-Indic digits; calibrate's reader refuses both
    try:
        return float(text)
    except ValueError:
        return None


def columns_of(spec, table: Table, map_path: str, where: str, line: int | None = None) -> list[int]:
    """0-based column indices of a column spec (numbers, ``"a-b"`` ranges, header names, lists of them); an error
    names the MAP's ``line`` where the spec stands."""
    if isinstance(spec, list):
        # flat only: a list of lists is no layout, and YAML aliases nest one to billions of cells (an alias bomb)
        nested = next((s for s in spec if isinstance(s, (list, dict))), None)
        if nested is not None:
            raise MeasurementFileError(
                map_path,
                f"{where}: a list of columns holds numbers, ranges or names, not {type(nested).__name__}s",
                line=line,
            )
        return [c for s in spec for c in columns_of(s, table, map_path, where, line)]
    header = table.header or []
    if isinstance(spec, str) and spec in header:
        if header.count(spec) > 1:  # the first would be taken without a word
            raise MeasurementFileError(
                table.path,
                f"{where}: the header names column {spec!r} {header.count(spec)} times: rename them",
                column=spec,
            )
        return [header.index(spec)]
    if isinstance(spec, str) and any(h.startswith(f"{spec}[") for h in header):
        return [i for i, h in enumerate(header) if re.fullmatch(rf"{re.escape(spec)}\[\d+\]", h)]
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", str(spec)) if not isinstance(spec, bool) else None
    if m is None:
        known = f"; its columns: {', '.join(header)}" if header else " (it has no header: give column numbers)"
        raise MeasurementFileError(map_path, f"{where}: {spec!r} is no column of {table.path}{known}", line=line)
    lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
    if lo < 1 or hi < lo:
        raise MeasurementFileError(map_path, f"{where}: {spec!r}: columns count from 1, ranges go up", line=line)
    return list(range(lo - 1, hi))


def numbers(table: Table, cols: list[int], read: dict) -> torch.Tensor:
    """The cells of ``cols`` as ``(rows, len(cols))`` float64; a missing or non-numeric cell is an error naming the
    file, line and column."""
    out = torch.empty(len(table.rows), len(cols), dtype=F64)
    for i, row in enumerate(table.rows):
        for j, c in enumerate(cols):
            name = table.header[c] if table.header and c < len(table.header) else f"{c + 1}"
            if c >= len(row):
                raise MeasurementFileError(
                    table.path, f"the row has {len(row)} cells, column {c + 1} is missing", line=table.lines[i]
                )
            v = _to_float(row[c], read)
            if v is None or not math.isfinite(v):
                raise MeasurementFileError(
                    table.path, f"{str(row[c])[:40]!r} is not a finite number", line=table.lines[i], column=name
                )
            out[i, j] = v
    return out


# ------------------------------------------------------------------------------------------------- the import
@dataclass
class _Inputs:
    """The INPUT files, each read once when a role first names it."""

    map_path: str
    paths: list[str]
    read: dict
    tables: dict = field(default_factory=dict)

    def table(self, k: int, doc: dict, key: str) -> Table:
        if k > len(self.paths):
            raise MeasurementFileError(
                self.map_path,
                f"'{key}' reads input {k}, the command gave {len(self.paths)} INPUT file(s)",
                line=_line(doc, key),
                column=key,
            )
        if k not in self.tables:
            self.tables[k] = read_table(self.paths[k - 1], self.read)
        return self.tables[k]


def _joints(doc: dict, inputs: _Inputs, angle: float) -> list[tuple[Table, torch.Tensor]]:
    """Per joints input, its table and the model joints ``(N, dof)`` [rad]: ``sign * reading + offset`` per listed
    column. One input pairs with every points input; several (``input: [1, 2]``) are each points input's own."""
    role = _role(doc["joints"], inputs.map_path, doc, "joints")
    out = []
    for k in role["input"]:
        table = inputs.table(k, doc, "joints")
        cols = columns_of(role["columns"], table, inputs.map_path, "joints.columns", role["line"])
        raw = numbers(table, cols, inputs.read)
        sign, offset = _sign_offset(doc, role, len(cols), inputs)
        out.append((table, (sign * raw + offset) * angle))
    return out


def _sign_offset(doc: dict, role: dict, dof: int, inputs: _Inputs) -> tuple[torch.Tensor, torch.Tensor]:
    """``joints.sign`` and ``joints.offset`` (default 1 and 0), checked."""
    out = []
    for key, default in (("sign", 1.0), ("offset", 0.0)):
        v = role.get(key, [default] * dof)
        ok = isinstance(v, list) and len(v) == dof and all(_to_float(x, {}) is not None for x in v)
        if not ok or (key == "sign" and any(float(x) not in (1.0, -1.0) for x in v)):
            raise MeasurementFileError(
                inputs.map_path,
                f"joints.{key} must list {dof} {'signs (1 or -1)' if key == 'sign' else 'numbers'}, got {v!r}",
                line=_line(doc["joints"], key) if isinstance(doc["joints"], dict) else None,
                column=key,
            )
        out.append(torch.tensor([float(x) for x in v], dtype=F64))
    return out[0], out[1]


def _rotation_rows(R: torch.Tensor, table: Table, cols: list[int]) -> torch.Tensor:
    """Rotation vectors ``(N, 3)`` of ``R (N, 3, 3)``; a matrix that is not a rotation names its row."""
    eye = torch.eye(3, dtype=F64)
    bad = ((R.transpose(-1, -2) @ R - eye).abs().amax((-1, -2)) > ROTATION_TOLERANCE) | (torch.linalg.det(R) <= 0)
    if bool(bad.any()):
        i = int(bad.nonzero()[0, 0])
        raise MeasurementFileError(
            table.path,
            f"columns {cols[0] + 1}..{cols[-1] + 1} hold no rotation (R^T R differs from I by more than "
            f"{ROTATION_TOLERANCE:g}, or det R <= 0)",
            line=table.lines[i],
        )
    return matrix_to_rotvec(R)


def _check_bottom_row(M: torch.Tensor, table: Table, cols: list[int], read: dict) -> None:
    """A 4x4 pose's last row must be ``0 0 0 1``. The refusal says what the columns look like instead: written
    column-major (the last *column* is ``0 0 0 1``), or the range off by one (the columns beside it hold the pose);
    an off-by-one range was called column-major."""
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=M.dtype)
    bad = (M[:, 3, :] - bottom).abs().amax(-1) > ROTATION_TOLERANCE
    if not bool(bad.any()):
        return
    i = int(bad.nonzero()[0, 0])
    row = " ".join(f"{float(x):g}" for x in M[i, 3])
    if bool(((M[:, :, 3] - bottom).abs().amax(-1) <= ROTATION_TOLERANCE).all()):
        why = "its last column is 0 0 0 1 in every row: a matrix written column-major? give its columns row-major"
    else:
        why = "check matrix.columns"
        for shift in (-1, 1, -2, 2):
            moved = [c + shift for c in cols]
            if min(moved) < 0 or any(max(moved) >= len(r) for r in table.rows):
                continue
            try:
                near = numbers(table, moved, read).reshape(-1, 4, 4)
            except MeasurementFileError:
                continue
            if bool(((near[:, 3, :] - bottom).abs().amax(-1) <= ROTATION_TOLERANCE).all()):
                why = (
                    f"columns {moved[0] + 1}..{moved[-1] + 1} hold a row-major pose in every row: the range is off "
                    f"by {abs(shift)}; write matrix.columns: {moved[0] + 1}-{moved[-1] + 1}"
                )
                break
    raise MeasurementFileError(
        table.path,
        f"columns {cols[0] + 1}..{cols[-1] + 1} are read as a row-major 4x4 pose, whose last row must be "
        f"0 0 0 1; it is {row} ({why})",
        line=table.lines[i],
    )


def _pose(role_key: str, role: dict, table: Table, inputs: _Inputs, length: float):
    """``(p (N, 3) [m] or None, r (N, 3) [rad] or None)`` of one points table for ``position``, ``matrix`` (16 or
    12 values, row-major) or ``quaternion`` (``order: wxyz`` default, or ``xyzw``)."""
    cols = columns_of(role["columns"], table, inputs.map_path, f"{role_key}.columns", role["line"])
    v = numbers(table, cols, inputs.read)
    want = {"position": (3,), "matrix": (16, 12), "quaternion": (4,)}[role_key]
    several = role_key == "position" and len(cols) > 3 and len(cols) % 3 == 0  # reflectors side by side in a row
    if len(cols) not in want and not several:
        raise MeasurementFileError(
            inputs.map_path,
            f"{role_key}.columns names {len(cols)} columns, {' or '.join(map(str, want))} expected"
            + (" (or 3 per reflector, several reflectors in one row)" if role_key == "position" else ""),
        )
    if role_key == "position":
        return (v * length).reshape(v.shape[0], -1, 3).squeeze(1), None
    if role_key == "matrix":
        M = v.reshape(-1, len(cols) // 4, 4)
        if M.shape[1] == 4:
            _check_bottom_row(M, table, cols, inputs.read)
        return M[:, :3, 3] * length, _rotation_rows(M[:, :3, :3], table, cols)
    order = role.get("order", "wxyz")
    if order not in ("wxyz", "xyzw"):
        raise MeasurementFileError(inputs.map_path, f"quaternion.order must be wxyz or xyzw, got {order!r}")
    w, x, y, z = (v if order == "wxyz" else v[:, [3, 0, 1, 2]]).unbind(-1)
    n = torch.stack([w, x, y, z], -1).norm(dim=-1)
    if bool(((n - 1).abs() > 1e-3).any()):
        i = int(((n - 1).abs() > 1e-3).nonzero()[0, 0])
        raise MeasurementFileError(
            table.path, f"the quaternion's norm is {float(n[i]):.6g}, not 1", line=table.lines[i]
        )
    w, x, y, z = w / n, x / n, y / n, z / n
    R = torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    return None, matrix_to_rotvec(R)


def _points(doc: dict, inputs: _Inputs, joint_tables: list[Table], length: float) -> list[tuple[int, Table, dict]]:
    """Per points input ``(input number, table, {"p": .., "r": ..})``; every table pairs row by row with the
    joints' (the same table, or as many rows): the one joints input's, or with several its own input's."""
    joints = joint_tables[0]
    keys = [k for k in ("position", "matrix", "quaternion") if k in doc]
    if "matrix" in keys and len(keys) > 1:
        raise MeasurementFileError(inputs.map_path, "a 'matrix' holds position and orientation: give it alone")
    roles = {k: _role(doc[k], inputs.map_path, doc, k) for k in keys}
    given = {tuple(r.get("input") if isinstance(doc[k], dict) and "input" in doc[k] else []) for k, r in roles.items()}
    if len(given) > 1:
        raise MeasurementFileError(inputs.map_path, f"{' and '.join(keys)} must read the same inputs")
    numbers_in = list(next(iter(given))) if given and next(iter(given)) else [inputs.paths.index(joints.path) + 1]
    if len(joint_tables) > 1:
        _check_own_joints(doc, inputs, joint_tables, numbers_in)
    out = []
    for i, k in enumerate(numbers_in):
        table = inputs.table(k, doc, keys[0] if keys else "joints")
        joints = joint_tables[i] if len(joint_tables) > 1 else joint_tables[0]
        if len(table.rows) != len(joints.rows):
            raise MeasurementFileError(
                table.path,
                f"{len(table.rows)} rows, the joints' file {joints.path} has {len(joints.rows)}: rows pair by order",
            )
        pose = {"p": None, "r": None}
        for key, role in roles.items():
            p, r = _pose(key, role, table, inputs, length)
            pose["p"] = p if p is not None else pose["p"]
            pose["r"] = r if r is not None else pose["r"]
        if pose["p"] is not None and pose["p"].dim() == 3:  # several reflectors per row: one points input each
            if pose["r"] is not None:
                raise MeasurementFileError(
                    inputs.map_path,
                    "position.columns names several reflectors per row: an orientation goes with one reflector",
                    line=roles["position"]["line"],
                )
            out += [(k, table, {"p": pose["p"][:, j], "r": None}) for j in range(pose["p"].shape[1])]
        else:
            out.append((k, table, pose))
    return out


def _check_own_joints(doc: dict, inputs: _Inputs, joint_tables: list[Table], numbers_in: list[int]) -> None:
    """Several joints inputs are each points input's own: the same inputs, in the same order."""
    own = [inputs.paths.index(t.path) + 1 for t in joint_tables]
    if own != numbers_in:
        raise MeasurementFileError(
            inputs.map_path,
            f"'joints' reads inputs {own} and the points inputs {numbers_in}: several joints inputs are each points "
            "input's own (list the same inputs in the same order), one joints input pairs with every points input",
            line=_line(doc, "joints"),
        )


def _label_cell(cell) -> str:
    if isinstance(cell, float) and cell.is_integer():
        return str(int(cell))
    return str(cell).strip()


def _labels(doc: dict, key: str, points: list, inputs: _Inputs) -> list[str] | None:
    """The ``station`` or ``probe`` name of every output row (points inputs in order, rows in order), or None."""
    spec = doc.get(key)
    if spec is None:
        return None
    if isinstance(spec, list):
        if len(spec) != len(points):
            raise MeasurementFileError(
                inputs.map_path,
                f"'{key}' names {len(spec)} inputs, the points come from {len(points)}",
                line=_line(doc, key),
                column=key,
            )
        bad = [name for name in spec if not _valid_label(str(name))]
        if bad:
            raise MeasurementFileError(
                inputs.map_path,
                f"'{key}': {bad[0]!r} is no name (non-empty, no ',', quotes or line breaks)",
                line=_line(doc, key),
                column=key,
            )
        return [str(name) for (_, table, _), name in zip(points, spec) for _ in table.rows]
    if isinstance(spec, dict) and set(spec) == {"column"}:
        out = []
        for _, table, _ in points:
            cols = columns_of(spec["column"], table, inputs.map_path, f"{key}.column", _line(doc, key))
            if len(cols) != 1:
                raise MeasurementFileError(inputs.map_path, f"'{key}.column' names {len(cols)} columns, not one")
            for row, line in zip(table.rows, table.lines):
                name = _label_cell(row[cols[0]]) if cols[0] < len(row) else ""
                if not _valid_label(name):
                    raise MeasurementFileError(
                        table.path, f"{name!r} is no {key} name (non-empty, no quotes)", line=line, column=key
                    )
                out.append(name)
        return out
    if isinstance(spec, dict) and set(spec) == {"block"}:
        return [str(b) for _, table, _ in points for b in table.blocks]
    raise MeasurementFileError(
        inputs.map_path,
        f"'{key}' is a list of names (one per points input), {{column: ..}} or {{block: ..}}",
        line=_line(doc, key),
        column=key,
    )


def _extra(doc: dict, table: Table, inputs: _Inputs) -> dict[str, torch.Tensor]:
    """``extra: {name: columns}`` of the joints' table; a name over k > 1 columns becomes name1..namek."""
    spec = doc.get("extra", {})
    if not isinstance(spec, dict):
        raise MeasurementFileError(inputs.map_path, "'extra' maps names to columns", line=_line(doc, "extra"))
    out = {}
    for name, cols_spec in spec.items():
        cols = columns_of(cols_spec, table, inputs.map_path, f"extra.{name}", _line(spec, name))
        v = numbers(table, cols, inputs.read)
        names = [str(name)] if len(cols) == 1 else [f"{name}{i + 1}" for i in range(len(cols))]
        bad = [n for n in names if n not in ("t", "temperature") and not _valid_extra_name(n)]
        if bad:
            raise MeasurementFileError(
                inputs.map_path,
                f"extra: {bad[0]!r} is a column of the format or not a name (no ',', quotes, leading '#')",
                line=_line(spec, name),
                column=str(name),
            )
        out.update({n: v[:, i].contiguous() for i, n in enumerate(names)})
    return _load(doc, table, inputs, out)


def _load(doc: dict, table: Table, inputs: _Inputs, extra: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``extra`` with ``payload: COL`` (kg) or ``[COL, X, Y, Z]`` (with its centre of mass in the flange frame, in
    the MAP's length unit) and ``torques: COLS`` (N m, one per joint) of the joints' table, the load columns of both
    validated together (a centre of mass from ``extra`` without a payload is refused as calibrate refuses it)."""
    from torchcal.data.load import PAYLOAD, PAYLOAD_COM, check_load

    out = {}
    for key in ("payload", "torques"):
        if key not in doc:
            continue
        cols = columns_of(doc[key], table, inputs.map_path, key, _line(doc, key))
        if key == "payload" and len(cols) not in (1, 4):
            raise MeasurementFileError(
                inputs.map_path,
                f"payload takes one column (kg) or four (kg, then the centre of mass x, y, z), got {len(cols)}",
                line=_line(doc, key),
                column=key,
            )
        v = numbers(table, cols, inputs.read)
        names = (PAYLOAD, *PAYLOAD_COM)[: len(cols)] if key == "payload" else [f"tau{k + 1}" for k in range(len(cols))]
        out.update({n: v[:, i].contiguous() for i, n in enumerate(names)})
    # by the names extra writes (tau: 1-6 writes tau1..tau6): a second tau1 replaced torques:'s without a word, and
    # extra's payload_x beside payload: left a centre of mass in part
    clash = sorted(set(extra) & ({*out, *PAYLOAD_COM, PAYLOAD} if PAYLOAD in out else set(out)))
    if clash:
        raise MeasurementFileError(
            inputs.map_path,
            f"extra writes {clash[0]!r}, a load column that 'payload:' or 'torques:' writes: give it there alone",
            line=_line(doc, "extra"),
            column="extra",
        )
    merged = {**extra, **out}
    if any(c in extra for c in PAYLOAD_COM) and PAYLOAD not in merged:
        raise MeasurementFileError(
            inputs.map_path,
            "extra writes the payload's centre of mass without the payload (kg): write 'payload: [KG, X, Y, Z]'",
            line=_line(doc, "extra"),
            column="extra",
        )
    length = doc.get("units", {}).get("length", "m")
    # the count of torques against the joints is checked on the rows (_check_torque_count), where both are known
    return check_load(table.path, merged, table.lines, 1, 0, length)


def _check_overlap(doc: dict, inputs: _Inputs) -> None:
    """Refuse a column that two roles read (``torques: 4-9`` over joints and x, y, z; ``payload: 7``, an x in mm,
    read as 812 kg): one column is one quantity, and either reading would be wrong without a word."""
    joints = _role(doc["joints"], inputs.map_path, doc, "joints")
    claims: dict[tuple[int, int], str] = {}
    for key in ("joints", "position", "matrix", "quaternion", "payload", "torques"):
        if key not in doc:
            continue
        role = joints if key == "joints" else _role(doc[key], inputs.map_path, doc, key)
        if key in ("joints", "payload", "torques"):  # the load columns are read from the joints' inputs
            numbers_in = joints["input"]
        elif isinstance(doc[key], dict) and "input" in doc[key]:
            numbers_in = role["input"]
        else:  # the points of the (first) joints input, as _points reads them
            numbers_in = joints["input"][:1]
        for k in numbers_in:
            table = inputs.table(k, doc, key)
            for c in columns_of(role["columns"], table, inputs.map_path, key, _line(doc, key)):
                first = claims.setdefault((k, c), key)
                if first != key:
                    raise MeasurementFileError(
                        inputs.map_path,
                        f"'{key}' reads column {c + 1} of {table.path}, which '{first}' reads too: one column holds "
                        "one quantity",
                        line=_line(doc, key),
                        column=key,
                    )


def _check_torque_count(doc: dict, inputs: _Inputs, q: torch.Tensor, extra: dict) -> None:
    """One torque per joint: ``torques:`` (or ``extra: {tau: ..}``) over as many columns as ``joints:``."""
    from torchcal.data.load import torque_columns

    names = torque_columns(list(extra))
    if names and len(names) != q.shape[1]:
        key = "torques" if "torques" in doc else "extra"
        raise MeasurementFileError(
            inputs.map_path,
            f"{key}: {len(names)} torque columns (tau1..tau{len(names)}) for {q.shape[1]} joints: one torque per joint",
            line=_line(doc, key),
            column=key,
        )


def _distinct_inputs(doc: dict, numbers: list[int], inputs: _Inputs) -> None:
    """Refuse two points inputs that the ``station``/``probe`` lists give the same names: each would be a second
    reading of one reflector at one placement for every row, rows the fit would count twice."""
    lists = [key for key in ("station", "probe") if isinstance(doc.get(key), list)]
    if (
        len(numbers) < 2
        or not lists
        or any(doc.get(key) is not None and key not in lists for key in ("station", "probe"))
    ):
        return  # names per row ({column: ..}, {block: ..}) may repeat: rows of one input differ
    seen = {}
    for i, names in enumerate(zip(*(doc[key] for key in lists), strict=True)):
        names = tuple(str(n) for n in names)
        if names in seen:
            raise MeasurementFileError(
                inputs.map_path,
                f"INPUTs {numbers[seen[names]]} and {numbers[i]} have the same {' and '.join(lists)} "
                f"{', '.join(names)}: name each input's reflector (probe) or placement (station) apart",
                line=_line(doc, lists[-1]),
                column=lists[-1],
            )
        seen[names] = i


def _check_unpaired_joints(doc: dict, inputs: _Inputs, joints: tuple, points: list) -> None:
    """Refuse a points input of its own that holds the joints' columns (by header name) with other values than the
    one joints input: each such file carries its own joints, and pairing its rows with another file's joints
    would give them the wrong poses without a word (``joints: {input: [..]}`` reads each input's own)."""
    table, _ = joints
    role = _role(doc["joints"], inputs.map_path, doc, "joints")
    names = role["columns"] if isinstance(role["columns"], list) else [role["columns"]]
    if not all(isinstance(n, str) and not re.fullmatch(r"[\d\s-]+", n) for n in names):
        return  # columns by number say nothing of what another file's columns are
    mine = None
    for k, other, _ in points:
        if other is table or other.header is None or not all(n in other.header for n in names):
            continue
        raw = numbers(other, columns_of(role["columns"], other, inputs.map_path, "joints.columns"), inputs.read)
        if mine is None:
            mine = numbers(table, columns_of(role["columns"], table, inputs.map_path, "joints.columns"), inputs.read)
        if raw.shape == mine.shape and not torch.equal(raw, mine):
            raise MeasurementFileError(
                inputs.map_path,
                f"input {k} ({other.path}) has its own joint columns {', '.join(names)}, with other readings than "
                f"the joints' input {table.path}, whose joints its rows would take: write 'joints: {{input: "
                f"[..]}}' with each points input to read its own joints",
                line=_line(doc, "joints"),
                column="joints",
            )


def _paired_joints(doc: dict, inputs: _Inputs, joints: list, k: int) -> tuple[torch.Tensor, dict, tuple]:
    """Every output row's joints, extra columns and source line: one joints input's for each of the ``k`` points
    inputs in turn, or each points input's own."""
    if len(joints) == 1:
        table, q = joints[0]
        extra = {n: v.repeat(k) for n, v in _extra(doc, table, inputs).items()}
        return q.repeat(k, 1), extra, tuple(table.lines) * k
    parts = [_extra(doc, table, inputs) for table, _ in joints]
    extra = {n: torch.cat([part[n] for part in parts]) for n in parts[0]}
    return torch.cat([q for _, q in joints]), extra, tuple(line for table, _ in joints for line in table.lines)


def _distinct_files(inputs: _Inputs) -> None:
    """Refuse one file given as two INPUTs: its rows would become two probes (or stations) of identical readings,
    and the fit would count each measurement twice (sigmas 1/sqrt(2) too small)."""
    from torchcal._inputs import check_regular

    stats = []
    for k, path in enumerate(inputs.paths, start=1):
        st = check_regular(path, "convert input", lambda m, path=path: MeasurementFileError(path, m))
        same = next((j for j, other in stats if (other.st_dev, other.st_ino) == (st.st_dev, st.st_ino)), None)
        if same is not None:
            raise MeasurementFileError(
                path,
                f"INPUTs {same} and {k} are the same file: each input is read once (a MAP role reads one input "
                "for several roles by its number)",
            )
        stats.append((k, st))


def _distinct_poses(inputs: _Inputs, points: list) -> None:
    """Refuse two points inputs whose every pose is the same: copies of one file, not two reflectors or placements."""
    for a in range(len(points)):
        for b in range(a):
            pa, pb = points[a][2], points[b][2]
            same = [
                pa[key] is not None
                and pb[key] is not None
                and pa[key].shape == pb[key].shape
                and torch.equal(pa[key], pb[key])
                for key in ("p", "r")
            ]
            if all(s or pa[key] is None for s, key in zip(same, ("p", "r"))):
                raise MeasurementFileError(
                    points[a][1].path,
                    f"INPUT {points[a][0]} has the very poses of INPUT {points[b][0]} ({points[b][1].path}), row for "
                    "row: a copy, which the fit would count twice; give each measured file once",
                )


def _check_mapped_units(doc: dict, inputs: _Inputs, joints: list, points: list) -> None:
    """What calibrate checks of the units, in the MAP's declared units, naming the MAP's ``units:`` as the fix
    (degrees read as radians reached |q| = 169.5, mm read as m 2,641 m, and only calibrate said so, naming its own
    flags)."""
    from torchcal.data.measurements import (
        _MAX_ABS_ANGLE_RAD,
        _MAX_MEDIAN_DISTANCE_M,
        _MIN_DEGREES_MOVED,
        _MIN_MEDIAN_DISTANCE_MM,
    )

    units = doc.get("units", {})
    length_unit, angle_unit = units.get("length", "m"), units.get("angle", "rad")
    where = f"the MAP's line {_line(doc, 'units')}" if "units" in doc else "a line of its own"
    ps = [(table, pose["p"] / LENGTH[length_unit]) for _, table, pose in points if pose["p"] is not None]
    if ps:
        median = torch.cat([p for _, p in ps]).norm(dim=-1).median().item()
        wrong = {"m": (median > _MAX_MEDIAN_DISTANCE_M, "mm", "millimetres", f"more than {_MAX_MEDIAN_DISTANCE_M:g}")}
        wrong["mm"] = (median < _MIN_MEDIAN_DISTANCE_MM, "m", "metres", f"less than {_MIN_MEDIAN_DISTANCE_MM:g}")
        bad, fix, looks, bound = wrong[length_unit]
        if bad:
            raise MeasurementFileError(
                inputs.map_path,
                f"the positions of {ps[0][0].path} look like {looks}: read as {length_unit}, their median distance "
                f"from the tracker is {median:.6g} {length_unit}, {bound} {length_unit}",
                line=_line(doc, "units"),
                hint=f"write 'units: {{length: {fix}}}' in the MAP ({where})",
            )
    for table, q in joints:
        q = q / ANGLE[angle_unit]
        if angle_unit == "rad" and bool((q.abs() > _MAX_ABS_ANGLE_RAD).any()):
            i, j = (int(x) for x in (q.abs() > _MAX_ABS_ANGLE_RAD).nonzero()[0])
            raise MeasurementFileError(
                table.path,
                f"joint {j + 1} = {q[i, j].item():.6g} rad is more than one turn (2*pi): the joint readings look like "
                "degrees",
                line=table.lines[i],
                hint=f"write 'units: {{angle: deg}}' in the MAP ({where})",
            )
        largest = float(q.abs().max()) if q.numel() else 0.0
        if angle_unit == "deg" and _MIN_DEGREES_MOVED < largest <= _MAX_ABS_ANGLE_RAD:
            raise MeasurementFileError(
                table.path,
                f"the joint readings look like radians although the MAP declares degrees: every |q| is at most 2*pi "
                f"(the largest {largest:.6g}), so as degrees the robot would never move more than 6.3 deg",
                hint=f"write 'units: {{angle: rad}}' in the MAP, or leave 'angle' out ({where})",
            )


def import_mapped(map_path: str | os.PathLike, paths: list[str]) -> Measurements:
    """The measurements the MAP reads from ``paths`` (the INPUT files, numbered from 1), in SI units.

    Rows: per points input in order (one per probe or station where ``probe``/``station`` lists them), its rows in
    order, each with the joints of the row of the same number.

    Raises:
        MeasurementFileError: the MAP or an input, naming the file, line and column.
    """
    doc = read_map(map_path)
    units = doc.get("units", {})
    length, angle = LENGTH[units.get("length", "m")], ANGLE[units.get("angle", "rad")]
    inputs = _Inputs(str(map_path), [str(p) for p in paths], doc.get("read", {}))
    _distinct_files(inputs)
    joints = _joints(doc, inputs, angle)
    points = _points(doc, inputs, [t for t, _ in joints], length)
    _check_overlap(doc, inputs)
    if len(points) > 1 and doc.get("probe") is None and doc.get("station") is None:
        raise MeasurementFileError(
            inputs.map_path, "the points come from several inputs: name them, 'probe: [..]' or 'station: [..]'"
        )
    if len(joints) == 1:
        _check_unpaired_joints(doc, inputs, joints[0], points)
    q, extra, lines = _paired_joints(doc, inputs, joints, len(points))
    _check_torque_count(doc, inputs, q, extra)
    cat = [pose[key] for _, _, pose in points for key in ("p", "r")]
    p = torch.cat([pose["p"] for _, _, pose in points]) if cat[0] is not None else None
    r = torch.cat([pose["r"] for _, _, pose in points]) if cat[1] is not None else None
    labels = {}
    for key in ("station", "probe"):
        names = _labels(doc, key, points, inputs)
        if names is not None:
            labels[key], labels[f"{key}_names"] = labels_of(names)
    _distinct_inputs(doc, [n for n, _, _ in points], inputs)  # after _labels: the lists' lengths are checked
    _distinct_poses(inputs, points)
    _check_mapped_units(doc, inputs, joints, points)
    return Measurements(
        q=q,
        p=p,
        r=r,
        t=extra.pop("t", None),
        temperature=extra.pop("temperature", None),
        extra=extra,
        lines=lines,
        meta={"converted_from": ", ".join(Path(x).name for x in paths)},
        **labels,
    )


def orientation_note(map_path: str | os.PathLike) -> str:
    """What an orientation read by the MAP (``matrix:`` or ``quaternion:``) does downstream, and the MAP that writes
    positions alone: a 4x4 pose made every fit 6-D (3.3x the CPU of a position fit) without a word."""
    doc = read_map(map_path)
    key = "matrix" if "matrix" in doc else "quaternion"
    role = _role(doc[key], str(map_path), doc, key)
    where = f"input: {role['input'][0] if len(role['input']) == 1 else role['input']}, "
    if key == "quaternion":
        fix = "leave out 'quaternion:'"
    else:
        m = re.fullmatch(r"\s*(\d+)\s*-\s*(\d+)\s*", str(role["columns"]))
        if m is not None and int(m.group(2)) - int(m.group(1)) + 1 in (12, 16):
            a = int(m.group(1))
            fix = f"write 'position: {{{where}columns: [{a + 3}, {a + 7}, {a + 11}]}}' instead of 'matrix:'"
        else:
            fix = "write 'position:' with the matrix's translation columns (its 4th, 8th and 12th) instead of 'matrix:'"
    return (
        f"the rows carry the probe's orientation (rx, ry, rz from '{key}:'): calibrate fits position and orientation "
        f"(6-D, about 3x the CPU of positions alone); for positions alone, {fix}"
    )


def convert_mapped(map_path, paths: list[str], out, *, written_by: str | None = None) -> Measurements:
    """:func:`import_mapped`, then the measurement file ``out`` written (atomically; nothing on an error)."""
    if not paths:
        raise OptionError("convert --map needs at least one INPUT file")
    m = import_mapped(map_path, paths)
    write_measurements(out, m, written_by=written_by)
    return m
