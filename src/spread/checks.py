"""One check of a whole-number setting, one of a true-or-false setting and one of a list that names each thing once,
for every command (on the lowest floor: any module may ask them).

A count, a size or a seed is a whole number: an ``int`` (numpy's too), never a ``bool`` (``True`` is 1 to Python)
and never a float — not even ``3.0``: a sweep's ``interval(2,4)`` draws ``3.274``, which ``int()`` quietly made 3,
so two points of a sweep ran one setting under two names. The error names the key as the user wrote it.
"""

from __future__ import annotations

import numbers


def is_whole(value) -> bool:
    """Whether ``value`` is a whole number (module docstring)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def whole_number(value, key: str, least: int = 0, *, null: str | None = None, where: str = "",
                 note: str = "") -> int | None:
    """``value`` as an ``int`` when it is a whole number ≥ ``least``; None when it is None and ``null`` says what
    null means (``"torch's default"``); else ``ValueError``: ``<key>=<value> <where>: expected a whole number ≥
    <least>``, with ``, or null for <null>`` and `` <note>`` appended."""
    if value is None and null is not None:
        return None
    if not is_whole(value) or int(value) < least:
        said = f"{key}={value!r}" + (f" {where}" if where else "")
        tail = (f", or null for {null}" if null is not None else "") + (f" {note}" if note else "")
        raise ValueError(f"{said}: expected a whole number ≥ {least}{tail}")
    return int(value)


def true_or_false(value, key: str) -> bool:
    """``value`` when it is a bool; else ``ValueError``: ``<key>=<value>: expected true or false`` (``figures=maybe``
    was read as true: a non-empty string is truthy)."""
    if not isinstance(value, bool):
        raise ValueError(f"{key}={value!r}: expected true or false")
    return value


def listed_once(values, key: str, each: str = "row") -> list:
    """``values`` as a list when none is listed twice; else ``ValueError``: ``<key>: <first repeat> is listed twice
    in <values>; give each <each> once``. A row or a seed asked twice is one thing counted as two: a table holds one
    row of it, a mean over seeds one run twice with no spread between them."""
    values = list(values)
    twice = [v for v in values if values.count(v) > 1]
    if twice:
        raise ValueError(f"{key}: {twice[0]!r} is listed twice in {values}; give each {each} once")
    return values
