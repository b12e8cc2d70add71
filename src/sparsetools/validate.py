"""Shared checks of parameter values: one function per rule, naming the parameter.

Every command and library function validates with these, so one rule reads the same
everywhere (``--resize: must be a finite number > 0, got -1``): the error is a
:class:`~sparsetools.errors.ParameterError` whose ``param`` the command line prints as the
option. Parsers of the small text formats options use (``WxH``, ``TOP,LEFT,H,W``) live here
too, so the command line and the library parse them the same way.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from .errors import ParameterError

__all__ = [
    "check_choice",
    "check_int_range",
    "check_non_negative",
    "check_positive",
    "check_probability",
    "parse_crop",
    "parse_size",
]


def _number(value, name: str) -> float:
    if isinstance(value, bool):
        raise ParameterError(f"must be a number, got {value!r}", param=name)
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"must be a number, got {value!r}", param=name) from None


def check_positive(value, name: str, *, allow_none: bool = False) -> float | None:
    """``value`` as a float when it is finite and > 0 (None passes with ``allow_none``)."""
    if value is None and allow_none:
        return None
    v = _number(value, name)
    if not (math.isfinite(v) and v > 0):
        raise ParameterError(f"must be a finite number > 0, got {value}", param=name)
    return v


def check_non_negative(value, name: str, *, allow_none: bool = False) -> float | None:
    """``value`` as a float when it is finite and >= 0 (None passes with ``allow_none``)."""
    if value is None and allow_none:
        return None
    v = _number(value, name)
    if not (math.isfinite(v) and v >= 0):
        raise ParameterError(f"must be a finite number >= 0, got {value}", param=name)
    return v


def check_probability(value, name: str, *, open_low: bool = True) -> float:
    """``value`` in (0, 1] (``open_low``) or [0, 1]."""
    v = _number(value, name)
    ok = (0 < v <= 1) if open_low else (0 <= v <= 1)
    if not (math.isfinite(v) and ok):
        interval = "(0, 1]" if open_low else "[0, 1]"
        raise ParameterError(f"must be in {interval}, got {value}", param=name)
    return v


def check_int_range(value, name: str, *, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an int in ``[low, high]`` (either bound optional)."""
    try:
        if isinstance(value, bool):
            raise TypeError
        iv = value.__index__() if hasattr(value, "__index__") else int(str(value).strip())
    except (TypeError, ValueError):
        raise ParameterError(f"must be an integer, got {value!r}", param=name) from None
    if (low is not None and iv < low) or (high is not None and iv > high):
        bounds = [
            b for b in (low is not None and f">= {low}", high is not None and f"<= {high}") if b
        ]
        raise ParameterError(f"must be {' and '.join(bounds)}, got {value}", param=name)
    return iv


def check_choice(value, name: str, choices: Iterable[str]) -> str:
    """``value`` when it is one of ``choices``."""
    choices = tuple(choices)
    if value not in choices:
        raise ParameterError(
            f"must be one of {', '.join(map(str, choices))}, got {value!r}", param=name
        )
    return value


def parse_size(text: str, name: str = "image_size") -> tuple[int, int]:
    """``"1242x375"`` -> ``(1242, 375)``: width and height, both > 0."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise ParameterError(f"expected WxH such as 1242x375, got {text!r}", param=name) from None
    if w <= 0 or h <= 0:
        raise ParameterError(f"width and height must be positive, got {text!r}", param=name)
    return w, h


def parse_crop(value, name: str = "crop") -> tuple[int, int, int, int]:
    """``"100,0,350,800"`` (or a 4-sequence) -> ``(top, left, height, width)``.

    TOP, LEFT >= 0 and H, W > 0 (pixels).
    """
    if isinstance(value, str):
        try:
            parts = tuple(int(v) for v in value.split(","))
        except ValueError:
            raise ParameterError(
                f"expected TOP,LEFT,H,W as integers, got {value!r}", param=name
            ) from None
    else:
        try:
            parts = tuple(int(v) for v in value)
        except (TypeError, ValueError):
            raise ParameterError(f"expected TOP,LEFT,H,W, got {value!r}", param=name) from None
    if len(parts) != 4:
        raise ParameterError(f"expected four integers TOP,LEFT,H,W, got {value!r}", param=name)
    top, left, h, w = parts
    if top < 0 or left < 0 or h <= 0 or w <= 0:
        raise ParameterError(f"TOP, LEFT must be >= 0 and H, W > 0, got {value!r}", param=name)
    return parts
