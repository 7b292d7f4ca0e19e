"""Time stamps: integer nanoseconds from input to output, seconds only where a human reads them.

A ROS header stamp is ``(sec, nanosec)``; as one int64 of nanoseconds it is exact for any
date a vehicle will see. Float seconds at today's epoch resolve only ~0.24 us, so every
conversion to and from text goes through decimal digits, never through a float.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

Stamps = NDArray[np.int64]
MAX_SECONDS: int = 9_000_000_000
"""Largest magnitude (s) of a stamp: int64 nanoseconds end at about 9.22e9 s (year 2262)."""
ROS_MAX_SECONDS: int = 2**31 - 1
"""Largest ``sec`` of a ROS stamp: ``builtin_interfaces/Time.sec`` is int32 (2038-01-19). A stamp
written to a bag is in ``0 .. ROS_MAX_SECONDS`` s (``sec`` at most this, ``nanosec`` below 1e9)."""


def split_stamp(stamp_ns: Any) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(sec, nanosec)`` of integer nanosecond stamps (floor division, nanosec in [0, 1e9))."""
    s = np.asarray(stamp_ns, dtype=np.int64)
    return s // NS_PER_S, s % NS_PER_S


def join_stamp(sec: Any, nanosec: Any) -> NDArray[np.int64]:
    """Integer nanoseconds of ``(sec, nanosec)`` pairs."""
    return np.asarray(sec, dtype=np.int64) * NS_PER_S + np.asarray(nanosec, dtype=np.int64)


def seconds_to_ns(seconds: Any) -> NDArray[np.int64]:
    """Float seconds (a rate, a duration, a simulated clock) to the nearest integer nanoseconds."""
    t = np.asarray(seconds, dtype=float)
    whole = np.floor(t)
    return whole.astype(np.int64) * NS_PER_S + np.rint((t - whole) * NS_PER_S).astype(np.int64)


def ns_to_seconds(stamp_ns: Any) -> NDArray[np.float64]:
    """Integer nanoseconds to float seconds, for plots and printed summaries only."""
    sec, nsec = split_stamp(stamp_ns)
    return sec.astype(float) + nsec.astype(float) * 1e-9


def parse_seconds(text: str) -> int:
    """Decimal seconds as text (``1700000000.123456789``, ``0.02``, ``1.7e9``) to exact nanoseconds.

    More than nine decimals are rounded to the nearest nanosecond. Raises :class:`InputError`
    for text that is not a finite number or beyond :data:`MAX_SECONDS`.
    """
    try:
        value = Decimal(text.strip())
    except InvalidOperation:
        raise InputError(f"not a time in seconds: {text!r}") from None
    if not value.is_finite():
        raise InputError(f"not a finite time in seconds: {text!r}")
    if abs(value) >= MAX_SECONDS:
        raise InputError(f"time {text.strip()} s is out of range (integer nanoseconds hold +-{MAX_SECONDS} s)")
    return int((value * NS_PER_S).to_integral_value())


def parse_seconds_column(texts: list[str]) -> NDArray[np.int64]:
    """:func:`parse_seconds` of every text of a column, vectorised when they are plain
    ``digits[.digits]`` with at most nine decimals (what :func:`format_seconds` writes);
    otherwise one by one (same results, same errors)."""
    plain = _plain_seconds(texts)
    if plain is None:
        plain = _digit_seconds(texts)
    if plain is not None:
        return plain
    return np.array([parse_seconds(t) for t in texts], dtype=np.int64)


def _digit_seconds(texts: list[str]) -> NDArray[np.int64] | None:
    """:func:`parse_seconds_column` of texts that are all ``digits`` or ``digits.digits`` (1-12 whole digits,
    up to 9 decimals, ``str.isdecimal``: a superscript is a digit, not a decimal) below :data:`MAX_SECONDS`, by
    numpy's string functions; None otherwise."""
    a = np.asarray(texts, dtype=str)
    if a.ndim != 1 or not len(a):
        return None
    whole, dot, frac = np.char.partition(a, ".").T
    plain = (np.char.str_len(whole) > 0) & (np.char.str_len(whole) <= 12) & np.char.isdecimal(whole)
    plain &= ((dot == "") & (frac == "")) | ((dot == ".") & (np.char.str_len(frac) <= 9) & np.char.isdecimal(frac))
    if not np.all(plain):
        return None
    seconds = whole.astype(np.int64)
    if seconds.max() >= MAX_SECONDS:  # (beyond: the one-by-one parse names it)
        return None
    return seconds * NS_PER_S + np.char.ljust(frac, 9, "0").astype(np.int64)  # no decimals: nine zeros


def _plain_seconds(texts: list[str]) -> NDArray[np.int64] | None:
    """:func:`parse_seconds_column` of texts that are all ``digits.digits`` (1-12 whole digits, 1-9
    decimals, ASCII), from one joined string; None otherwise."""
    if not isinstance(texts, list) or not texts or not isinstance(texts[0], str):
        return None
    try:
        joined = ",".join(texts)
    except TypeError:
        return None
    if joined.count(",") != len(texts) - 1:
        return None  # a text with a comma (a decimal comma is not a time)
    pieces = joined.replace(".", ",").split(",")
    if len(pieces) != 2 * len(texts):
        return None  # points and texts differ in number
    whole, frac = pieces[0::2], pieces[1::2]
    digits = "".join(whole) + "".join(frac)
    if not (digits.isascii() and digits.isdigit()):
        return None
    wl = np.fromiter(map(len, whole), np.int64, len(whole))
    fl = np.fromiter(map(len, frac), np.int64, len(frac))
    if wl.min() < 1 or wl.max() > 12 or fl.min() < 1 or fl.max() > 9:
        return None
    if np.any(np.fromiter(map(len, texts), np.int64, len(texts)) != wl + fl + 1):
        return None  # a text with two points beside one without: the pieces fell out of line
    seconds = np.array(whole, dtype=np.int64)
    if seconds.max() >= MAX_SECONDS:
        return None  # out of range: the one-by-one parse names it
    return seconds * NS_PER_S + np.array(frac, dtype=np.int64) * 10 ** (9 - fl)


def format_seconds(stamp_ns: int) -> str:
    """Exact decimal seconds with nine decimals (``-0.5 s`` is ``-0.500000000``)."""
    ns = int(stamp_ns)
    sign = "-" if ns < 0 else ""
    sec, nsec = divmod(abs(ns), NS_PER_S)
    return f"{sign}{sec}.{nsec:09d}"


def format_seconds_column(stamp_ns: Any) -> list[str]:
    """:func:`format_seconds` of every stamp of an array."""
    return [format_seconds(t) for t in np.asarray(stamp_ns, dtype=np.int64).tolist()]
