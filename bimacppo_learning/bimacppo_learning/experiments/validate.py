"""Checks for config values: each builder returns a function ``value -> None | message``.

A message completes the sentence "key 'x' ..." (``must be an integer, got 'many'``), so the
config loader can name the file and the key in front of it.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Iterable

Check = Callable[[Any], "str | None"]


def integer(lo: int | None = None, hi: int | None = None) -> Check:
    def check(v):
        if isinstance(v, bool) or not isinstance(v, int):
            return f"must be an integer, got {v!r}"
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            return f"must be in {lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}, got {v}"
        return None
    return check


def number(lo: float, hi: float | None = None, lo_open: bool = False) -> Check:
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return f"must be a finite number, got {v!r}"
        if v < lo or (lo_open and v == lo) or (hi is not None and v > hi):
            return f"must be in {'(' if lo_open else '['}{lo}, {hi if hi is not None else 'inf'}], got {v}"
        return None
    return check


def choice(options: Iterable) -> Check:
    options = tuple(options)

    def check(v):
        return None if v in options else f"must be one of {list(options)}, got {v!r}"
    return check


def text(optional: bool = False) -> Check:
    def check(v):
        if v is None and optional:
            return None
        return None if isinstance(v, str) and v else f"must be a non-empty string{' or null' if optional else ''}, got {v!r}"
    return check


def optional(inner: Check) -> Check:
    """``inner``, or null."""
    def check(v):
        return None if v is None else inner(v)
    return check


def items(item: Check, nonempty: bool = True) -> Check:
    """A list without repeats whose every element passes ``item``."""
    def check(v):
        if not isinstance(v, list) or (nonempty and not v):
            return f"must be a {'non-empty ' if nonempty else ''}list, got {v!r}"
        if len(set(map(repr, v))) != len(v):
            return f"must not repeat items, got {v!r}"
        for x in v:
            err = item(x)
            if err:
                return f"item {x!r}: {err}"
        return None
    return check
