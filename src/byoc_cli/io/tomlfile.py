"""Reading a small TOML file whatever it holds: size, nesting and key length bounded before
:mod:`tomllib` parses it.

:mod:`tomllib` recurses once per level of nested arrays and inline tables (a file of 50,000
``[`` ends in a ``RecursionError``) and builds one table per part of a dotted key (one key of
100,000 parts took 50 s and 3.5 GB). :func:`read_toml` reads the file through
:func:`~byoc_cli.io.inputs.read_input` (the size cap of its kind), then scans the text once,
in linear time, for the deepest nesting of a value and the longest dotted key or table name,
and refuses either past its bound in one message naming the key. What the scan lets through
is small enough for :mod:`tomllib`; its errors (and a ``RecursionError`` all the same) become
an :class:`~byoc_cli.errors.InputError`.
"""

from __future__ import annotations

import os
from typing import Any

from byoc_cli.errors import InputError
from byoc_cli.io.inputs import read_input

#: deepest nesting of arrays and inline tables in one value
MAX_DEPTH = 16
#: most parts of a dotted key or a table name (``a.b.c`` has 3)
MAX_KEY_PARTS = 8
#: most digits of one number (TOML's integers have at most 19; a float's digits beyond 17 are
#: lost), so that no number is converted from thousands of digits
MAX_DIGITS = 64
#: characters of a key shown in a message
_SHOWN = 40


class _Shape(ValueError):
    """A TOML text nested too deeply or with too long a key; the message names the key."""


def _shown(key: str) -> str:
    key = " ".join(key.split())
    return key if len(key) <= _SHOWN else key[: _SHOWN - 3] + "..."


def _skip_string(text: str, i: int) -> int:
    """The index just past the string that starts at ``text[i]`` (a quote)."""
    quote = text[i]
    triple = text.startswith(quote * 3, i)
    i += 3 if triple else 1
    n = len(text)
    while i < n:
        c = text[i]
        if c == "\\" and quote == '"':
            i += 2
            continue
        if c == "\n" and not triple:
            return i  # an unterminated string: tomllib reports it
        if c == quote:
            if not triple:
                return i + 1
            if text.startswith(quote * 3, i):
                # a closing triple quote may be followed by one or two more quotes
                end = i + 3
                while end < n and end < i + 5 and text[end] == quote:
                    end += 1
                return end
        i += 1
    return n


def check_toml_shape(
    text: str, max_depth: int = MAX_DEPTH, max_key_parts: int = MAX_KEY_PARTS
) -> None:
    """Refuse a TOML text whose values nest deeper than ``max_depth`` or whose keys or table
    names have more than ``max_key_parts`` dotted parts (one linear scan; strings and comments
    skipped).

    Raises:
        ValueError: naming the key (shortened) and the bound.
    """
    depth = 0
    key_start = 0  # where the key of the current top-level line starts
    key = ""  # the key of the value being read, after the table's name
    table = ""  # the name of the last table header
    header = -1  # where the name of the table header being read starts (-1: none)
    dots = 0  # dots of the key or dotted run being read
    digits = 0  # length of the run of digits being read
    n = len(text)
    i = 0
    line_start = True
    while i < n:
        c = text[i]
        if c.isdigit() or (c == "_" and digits):
            digits += 1
            if digits > MAX_DIGITS:
                raise _Shape(
                    f"{_shown(key) or 'a value'}: a number of more than {MAX_DIGITS} digits"
                )
            line_start = False
            i += 1
            continue
        digits = 0
        if c in "\"'":
            i = _skip_string(text, i)
            line_start = False
            continue
        if c == "#":
            end = text.find("\n", i)
            i = n if end < 0 else end
            continue
        if c == "\n":
            if depth == 0:
                key_start, dots, line_start = i + 1, 0, True
            i += 1
            continue
        if c in " \t\r":
            i += 1
            continue
        if c == "=":
            if depth == 0:
                name = text[key_start:i].strip()
                key = f"{table}.{name}" if table else name
            dots = 0
        elif c == ".":
            dots += 1
            if dots >= max_key_parts:
                where = key
                if depth == 0:
                    where = text[header if header >= 0 else key_start : i].lstrip(" \t[")
                raise _Shape(f"key {_shown(where)!r} has more than {max_key_parts} dotted parts")
        elif c in "[{":
            if depth == 0 and line_start and c == "[":  # a table header: its name only
                dots, header = 0, i + 1
            elif depth == 0 and c == "[" and text[key_start:i].strip() == "[":  # [[array]]
                header = i + 1
            else:
                depth += 1
                dots = 0
                if depth > max_depth:
                    raise _Shape(
                        f"{_shown(key) or 'a value'}: nested deeper than {max_depth} levels"
                    )
        elif c in "]}":
            if depth == 0 and header >= 0:  # the end of a table header
                table, header = text[header:i].strip(), -1
            depth = max(depth - 1, 0)
        elif c == ",":
            dots = 0
        line_start = False
        i += 1


def read_toml(
    path: str | os.PathLike[str],
    kind: str,
    what: str = "TOML",
    max_depth: int = MAX_DEPTH,
    max_key_parts: int = MAX_KEY_PARTS,
) -> dict[str, Any]:
    """The tree of the TOML file ``path``, read within the size cap of ``kind``
    (:data:`~byoc_cli.io.inputs.SIZE_CAPS`) and the bounds of :func:`check_toml_shape`;
    ``what`` names the content in a parse error (``"is not a TOML recipe (...)"``).

    Raises:
        InputError: the file cannot be read, is too large, is not UTF-8 TOML, nests too
            deeply or has too long a key (one line naming the file and the key).
    """
    import tomllib

    try:
        text = read_input(path, kind).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        check_toml_shape(text, max_depth, max_key_parts)
        return tomllib.loads(text)
    except _Shape as exc:
        raise InputError(path, str(exc)) from None
    except RecursionError:
        raise InputError(path, f"nested deeper than {max_depth} levels") from None
    except ValueError as exc:  # TOMLDecodeError, and an integer of too many digits
        raise InputError(path, f"is not {what} ({exc})") from None
