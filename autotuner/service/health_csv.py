"""A historian export as a loop record: a CSV file with a header row and the columns ``t`` (seconds, or ISO-8601
timestamps), ``sp``, ``pv``, ``mv`` and optionally ``mode`` (``AUTO``/``MAN``); other columns are ignored.

:func:`read_record` raises :class:`CsvError` naming the file, the line and the column of the first problem.
"""

from __future__ import annotations

import csv
import math
import os
from datetime import datetime

import numpy as np

from autotuner.engine.health.record import LoopRecord

REQUIRED = ("t", "sp", "pv", "mv")
MODES = {"AUTO": True, "MAN": False}


class CsvError(ValueError):
    """A CSV file that is no loop record; the message names the line and column."""


def _seconds(text: str) -> float | datetime:
    """A time cell: a number of seconds, or an ISO-8601 timestamp."""
    try:
        return float(text)
    except ValueError:
        pass
    return datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith(("Z", "z")) else text)


def _times(cells: list[str], name: str) -> np.ndarray:
    """Seconds from the time cells (timestamps: seconds after the first row's)."""
    values: list[float | datetime] = []
    for line, text in enumerate(cells, start=2):
        try:
            values.append(_seconds(text))
        except ValueError:
            raise CsvError(f"{name}:{line}: column 't': {text!r} is neither seconds nor an ISO-8601 timestamp") from None
        if type(values[-1]) is not type(values[0]) or (
                isinstance(values[-1], datetime) and (values[-1].tzinfo is None) != (values[0].tzinfo is None)):
            raise CsvError(f"{name}:{line}: column 't': {text!r} mixes seconds, zoned and unzoned timestamps")
    if isinstance(values[0], datetime):
        start = values[0]
        return np.array([(v - start).total_seconds() for v in values])  # type: ignore[operator]
    return np.array(values, dtype=float)


def _numbers(cells: list[str], column: str, name: str) -> np.ndarray:
    out = np.empty(len(cells))
    for k, text in enumerate(cells):
        try:
            out[k] = float(text)
        except ValueError:
            raise CsvError(f"{name}:{k + 2}: column {column!r}: {text!r} is not a number") from None
        if not math.isfinite(out[k]):
            raise CsvError(f"{name}:{k + 2}: column {column!r}: {text!r} is not a finite number")
    return out


def read_record(path: str | os.PathLike[str]) -> LoopRecord:
    """The record in the CSV file ``path`` (lines counted from 1, the header line 1)."""
    name = os.fspath(path)
    try:
        with open(name, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise CsvError(f"{name}: cannot read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise CsvError(f"{name}: not a CSV text file: {exc}") from None
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise CsvError(f"{name}: empty: expected a header row with the columns t, sp, pv, mv (and mode)")
    header = [cell.strip().lower() for cell in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise CsvError(f"{name}:1: missing column {missing[0]!r} (the header has: {', '.join(rows[0])})")
    data = rows[1:]
    for line, row in enumerate(data, start=2):
        if len(row) != len(header):
            raise CsvError(f"{name}:{line}: {len(row)} fields, the header has {len(header)}")
    columns = {c: [row[header.index(c)].strip() for row in data] for c in (*REQUIRED, "mode") if c in header}
    for column, cells in columns.items():
        empty = next((k for k, text in enumerate(cells) if not text), None)
        if empty is not None:
            raise CsvError(f"{name}:{empty + 2}: column {column!r}: empty")
    if len(data) < 2:
        raise CsvError(f"{name}: {len(data)} data rows: a record needs at least 2")
    t = _times(columns["t"], name)
    back = np.flatnonzero(np.diff(t) <= 0.0)
    if len(back):
        line = int(back[0]) + 3
        raise CsvError(f"{name}:{line}: column 't': {columns['t'][line - 2]} is not after the line before's "
                       f"{columns['t'][line - 3]} (time must increase)")
    auto = None
    if "mode" in columns:
        bad = next((k for k, text in enumerate(columns["mode"]) if text.upper() not in MODES), None)
        if bad is not None:
            raise CsvError(f"{name}:{bad + 2}: column 'mode': {columns['mode'][bad]!r} is neither AUTO nor MAN")
        auto = np.array([MODES[text.upper()] for text in columns["mode"]])
    return LoopRecord.of(t, *(_numbers(columns[c], c, name) for c in ("sp", "pv", "mv")), auto)
