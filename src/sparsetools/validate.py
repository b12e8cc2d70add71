"""The one vocabulary of checks: one function per rule, naming the parameter.

Modelled on kornia's ``KORNIA_CHECK_SHAPE``: a rule reads the same wherever it is applied
(``--resize: must be a finite number > 0, got -1``), because every library function, every
settings record and every command line callback applies it through this module. The error is
a :class:`~sparsetools.errors.ParameterError` whose ``param`` the command line prints as the
option.

Where each kind of check lives (DESIGN.md, "one validation vocabulary"):

- the command line's callbacks only *parse* text (:func:`parse_size`, :func:`parse_crop`,
  :func:`parse_pair`, :func:`parse_int_list`);
- settings records validate their values once, in ``__post_init__``, with the ``check_*``
  functions;
- ``ops/`` checks arrays at its public boundary with :func:`check_array`,
  :func:`check_shape`, :func:`check_dtype`, :func:`check_all_finite`, :func:`check_points`
  and :func:`check_values` (``tests/test_architecture_ops.py`` holds it to that).

The syntaxes every command shares are defined here once: a size is ``WxH`` (``1242x375``), a
crop box is ``WxH+LEFT+TOP`` (``800x350+0+100``, ImageMagick's geometry), a pair or range is
``A,B``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence

import numpy as np

from .errors import ParameterError

__all__ = [
    "CROP_SYNTAX",
    "SIZE_SYNTAX",
    "check_all_finite",
    "check_array",
    "check_choice",
    "check_dtype",
    "check_finite",
    "check_flag",
    "check_increasing",
    "check_instance",
    "check_int_range",
    "check_multiple",
    "check_non_negative",
    "check_nonempty",
    "check_odd",
    "check_ordered",
    "check_pair",
    "check_points",
    "check_positive",
    "check_probability",
    "check_range",
    "check_same_length",
    "check_same_shape",
    "check_shape",
    "check_values",
    "format_crop",
    "is_legacy_crop",
    "parse_crop",
    "parse_frame_range",
    "parse_int_list",
    "parse_pair",
    "parse_size",
]

#: The one syntax of an image size on the command line (width first, as OpenCV and KITTI do).
SIZE_SYNTAX = "WxH"
#: The one syntax of a crop box: a ``WxH`` size at column LEFT, row TOP (ImageMagick geometry).
CROP_SYNTAX = "WxH+LEFT+TOP"


# -- numbers -----------------------------------------------------------------------------------


def _number(value, name: str) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise ParameterError(f"must be a number, got {value!r}", param=name)
    try:
        return float(value)
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"must be a number, got {value!r}", param=name) from None


def check_finite(value, name: str, *, allow_none: bool = False) -> float | None:
    """``value`` as a float when it is a finite number (None passes with ``allow_none``)."""
    if value is None and allow_none:
        return None
    v = _number(value, name)
    if not math.isfinite(v):
        raise ParameterError(f"must be a finite number, got {value}", param=name)
    return v


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


def check_range(
    value,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_none: bool = False,
) -> float | None:
    """``value`` as a finite float in the interval ``low .. high`` (either bound optional;
    ``*_open`` excludes the bound)."""
    if value is None and allow_none:
        return None
    v = _number(value, name)
    ok = math.isfinite(v)
    if low is not None:
        ok = ok and (v > low if low_open else v >= low)
    if high is not None:
        ok = ok and (v < high if high_open else v <= high)
    if not ok:
        lo = "" if low is None else f"{'(' if low_open else '['}{low:g}"
        hi = "" if high is None else f"{high:g}{')' if high_open else ']'}"
        if low is not None and high is not None:
            where = f"in {lo}, {hi}"
        elif low is not None:
            where = f"{'>' if low_open else '>='} {low:g}"
        elif high is not None:
            where = f"{'<' if high_open else '<='} {high:g}"
        else:
            where = "finite"
        raise ParameterError(f"must be a finite number {where}, got {value}", param=name)
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
        if isinstance(value, (bool, np.bool_)):
            raise TypeError
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        iv = value.__index__() if hasattr(value, "__index__") else int(str(value).strip())
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"must be an integer, got {value!r}", param=name) from None
    if (low is not None and iv < low) or (high is not None and iv > high):
        bounds = [
            b for b in (low is not None and f">= {low}", high is not None and f"<= {high}") if b
        ]
        raise ParameterError(f"must be {' and '.join(bounds)}, got {value}", param=name)
    return iv


def check_odd(value, name: str, *, low: int = 1, high: int | None = None) -> int:
    """``value`` as an odd int in ``[low, high]`` (a window centred on its pixel)."""
    iv = check_int_range(value, name, low=low, high=high)
    if iv % 2 == 0:
        raise ParameterError(f"must be odd (a window centred on its pixel), got {iv}", param=name)
    return iv


def check_multiple(value, name: str, *, of: int, low: int | None = None,
                   high: int | None = None) -> int:  # fmt: skip
    """``value`` as an int in ``[low, high]`` that is a multiple of ``of`` (a matcher's
    search range in whole blocks)."""
    iv = check_int_range(value, name, low=low, high=high)
    if iv % of:
        raise ParameterError(f"must be a multiple of {of}, got {iv}", param=name)
    return iv


def check_choice(value, name: str, choices: Iterable[str]) -> str:
    """``value`` when it is one of ``choices``."""
    choices = tuple(choices)
    try:
        ok = value in choices
    except TypeError:  # an unhashable value against a set-like choices
        ok = False
    if not ok:
        raise ParameterError(
            f"must be one of {', '.join(map(str, choices))}, got {value!r}", param=name
        )
    return value


def check_flag(value, name: str) -> bool:
    """``value`` as a bool when it is one (``True``/``False`` or a numpy bool; not 0, 1 or a
    string, which would read as a flag by accident)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ParameterError(f"must be True or False, got {value!r}", param=name)
    return bool(value)


def check_instance(value, name: str, types: type | tuple[type, ...]):
    """``value`` when it is an instance of ``types`` (a settings record, a calibration...)."""
    if not isinstance(value, types):
        want = " or ".join(t.__name__ for t in (types if isinstance(types, tuple) else (types,)))
        raise ParameterError(f"must be a {want}, got {type(value).__name__}", param=name)
    return value


def check_ordered(low, high, low_name: str, high_name: str) -> None:
    """``high > low`` for a pair of settings (``max_depth`` above ``min_depth``); either may be
    None (no bound)."""
    if low is None or high is None:
        return
    if not high > low:
        lo = "--" + low_name.lstrip("-").replace("_", "-")
        raise ParameterError(f"({high:g}) must be > {lo} ({low:g})", param=high_name)


def check_pair(
    value,
    name: str,
    *,
    low: float | None = None,
    high: float | None = None,
    strict: bool = False,
    integer: bool = False,
) -> tuple:
    """``value`` as an ordered ``(a, b)`` pair of finite numbers with ``a <= b``.

    ``low`` bounds ``a`` from below (``a > low`` when ``strict``, else ``a >= low``); ``high``
    bounds ``b`` from above. A single number stands for ``(v, v)``.
    """
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        value = (value, value)
    try:
        a, b = value
        a, b = _number(a, name), _number(b, name)
    except (TypeError, ValueError):
        raise ParameterError(
            f"must be a (low, high) pair of numbers, got {value!r}", param=name
        ) from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ParameterError(f"must be finite, got {value!r}", param=name)
    if integer and not (a.is_integer() and b.is_integer()):
        raise ParameterError(f"must be integers, got {value!r}", param=name)
    if a > b:
        raise ParameterError(f"range is inverted ({a:g} > {b:g})", param=name)
    if low is not None and (a <= low if strict else a < low):
        raise ParameterError(
            f"must be {'>' if strict else '>='} {low:g}, got {value!r}", param=name
        )
    if high is not None and b > high:
        raise ParameterError(f"must be <= {high:g}, got {value!r}", param=name)
    return (int(a), int(b)) if integer else (a, b)


# -- arrays ------------------------------------------------------------------------------------

_DIM = re.compile(r"^(?:(\d+)|([A-Za-z_]\w*)|\.\.\.)$")


def check_array(a, name: str) -> np.ndarray:
    """``a`` when it is a numpy array (no silent conversion of lists, tensors or None)."""
    if not isinstance(a, np.ndarray):
        raise ParameterError(f"must be a numpy array, got {type(a).__name__}", param=name)
    return a


def _parse_shape_spec(spec: str) -> list[list[str]]:
    alternatives = []
    for alt in spec.split("|"):
        text = alt.strip()
        if not (text.startswith("(") and text.endswith(")")):
            raise ValueError(f"bad shape spec {spec!r}")
        dims = [d.strip() for d in text[1:-1].split(",") if d.strip()]
        for d in dims:
            if not _DIM.match(d):
                raise ValueError(f"bad dimension {d!r} in shape spec {spec!r}")
        alternatives.append(dims)
    return alternatives


def _match_shape(shape: tuple[int, ...], dims: list[str]) -> dict[str, int] | None:
    if "..." in dims:
        k = dims.index("...")
        head, tail = dims[:k], dims[k + 1 :]
        if len(shape) < len(head) + len(tail):
            return None
        shape = shape[: len(head)] + shape[len(shape) - len(tail) :]
        dims = head + tail
    if len(shape) != len(dims):
        return None
    sizes: dict[str, int] = {}
    for n, d in zip(shape, dims, strict=True):
        if d.isdigit():
            if n != int(d):
                return None
        elif d in sizes and sizes[d] != n:
            return None
        else:
            sizes[d] = n
    return sizes


def check_shape(a, spec: str, name: str, *, nonempty: bool = False) -> dict[str, int]:
    """Check ``a.shape`` against ``spec`` and return the sizes of its named dimensions.

    ``spec`` is a tuple of dimensions, alternatives separated by ``|``: a number is a fixed
    size, a name any size (a name used twice must have one size), ``...`` any number of
    dimensions: ``"(H, W)"``, ``"(H, W) | (H, W, 3)"``, ``"(N, 3)"``, ``"(4, 4)"``,
    ``"(B, ...)"``.

    Parameters
    ----------
    a : numpy array (anything with ``.shape``)
    spec : str
    name : str
        The parameter, for the message.
    nonempty : bool
        Also refuse an array with no element.

    Returns
    -------
    dict
        Sizes of the named dimensions of the alternative that matched (``{"H": 375, ...}``).
    """
    shape = getattr(a, "shape", None)
    if shape is None:
        raise ParameterError(
            f"must be an array of shape {spec}, got {type(a).__name__}", param=name
        )
    # A list, not a generator: tuple(generator) over-allocates then shrinks, and CPython's
    # tuple free list keeps each shrunk block (a per-frame check would grow memory to ~100 KB).
    shape = tuple([int(n) for n in shape])
    for dims in _parse_shape_spec(spec):
        sizes = _match_shape(shape, dims)
        if sizes is not None:
            if nonempty and math.prod(shape) == 0:
                raise ParameterError(f"is empty (shape {shape})", param=name)
            return sizes
    raise ParameterError(f"must have shape {spec}, got {shape}", param=name)


_KIND_NAMES = {
    "b": "boolean",
    "i": "signed integer",
    "u": "unsigned integer",
    "f": "floating point",
    "c": "complex",
}


def check_dtype(a, name: str, allowed: str | Sequence) -> np.dtype:
    """``a.dtype`` when it is allowed: ``allowed`` is a string of numpy kind codes (``"fiu"``:
    any real number) or a sequence of dtypes (``(np.uint8,)``)."""
    dtype = getattr(a, "dtype", None)
    if dtype is None:
        raise ParameterError(f"must be an array, got {type(a).__name__}", param=name)
    if isinstance(allowed, str):
        if dtype.kind in allowed:
            return dtype
        want = " or ".join(_KIND_NAMES.get(k, k) for k in allowed)
    else:
        dtypes = [np.dtype(d) for d in allowed]
        if dtype in dtypes:
            return dtype
        want = " or ".join(str(d) for d in dtypes)
    raise ParameterError(f"must be {want}, got {dtype}", param=name)


def check_all_finite(a, name: str) -> None:
    """No NaN or infinite value in ``a`` (a float array; integer arrays always pass)."""
    arr = np.asarray(a)
    if arr.dtype.kind in "fc" and not np.isfinite(arr).all():
        raise ParameterError("holds NaN or infinite values", param=name)


def check_same_shape(a, b, name_a: str, name_b: str, *, dims: int | None = None) -> None:
    """``a`` and ``b`` have one shape (their first ``dims`` dimensions only, when given)."""
    sa, sb = tuple(a.shape), tuple(b.shape)
    if dims is not None:
        sa, sb = sa[:dims], sb[:dims]
    if sa != sb:
        raise ParameterError(
            f"is {sa} but {name_b} is {sb}: they must have one shape", param=name_a
        )


def _fmt_value(v) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{float(v):.4g}"


def check_values(a, name: str, *, low: float | None = None, high: float | None = None) -> None:
    """Every value of the array ``a`` lies in ``[low, high]`` (either bound optional); NaN
    never does. An empty array passes."""
    arr = np.asarray(a)
    if arr.size == 0:
        return
    lo, hi = arr.min(), arr.max()
    if (low is None or lo >= low) and (high is None or hi <= high):
        return
    got = f"got values in [{_fmt_value(lo)}, {_fmt_value(hi)}]"
    if low is not None and high is not None:
        want = f"lie in [{_fmt_value(low)}, {_fmt_value(high)}]"
    elif low is not None:
        want, got = f"be >= {_fmt_value(low)}", f"got a minimum of {_fmt_value(lo)}"
    else:
        want, got = f"be <= {_fmt_value(high)}", f"got a maximum of {_fmt_value(hi)}"
    raise ParameterError(f"values must {want}, {got}", param=name)


def check_nonempty(items, name: str) -> None:
    """``items`` (a sequence: scans, sweeps, panels, rings...) holds at least one element."""
    if len(items) == 0:
        raise ParameterError("must hold at least one item, got none", param=name)


def check_same_length(items, other, name: str, other_name: str) -> None:
    """One of ``items`` (labels, weights...) per element of ``other`` (maps, tiles...)."""
    if len(items) != len(other):
        raise ParameterError(
            f"{len(items)} {name} for {len(other)} {other_name}: give one per {other_name}",
            param=name,
        )


def check_increasing(a, name: str, *, nonempty: bool = True) -> np.ndarray:
    """``a`` as a 1-D float64 array of at least two strictly increasing finite values
    (bin edges, thresholds)."""
    arr = np.asarray(a, dtype=np.float64)
    check_shape(arr, "(K)", name, nonempty=nonempty)
    check_all_finite(arr, name)
    if arr.size < 2 or np.any(np.diff(arr) <= 0):
        raise ParameterError(
            f"must be at least two strictly increasing values, got {arr.tolist()[:6]}", param=name
        )
    return arr


def check_points(a, name: str = "points", *, nonempty: bool = False) -> int:
    """``a`` is a point cloud: an (N, C) array of real numbers with C >= 3 and x, y, z in its
    first three columns; returns C. With ``nonempty``, also refuse a cloud with no point.

    The array is not converted (``np.asarray`` a list before) and its values are not looked
    at: whether NaN coordinates are an error depends on the operation.
    """
    if not hasattr(a, "shape"):
        raise ParameterError(f"must be an (N, C>=3) array, got {type(a).__name__}", param=name)
    shape = tuple([int(n) for n in a.shape])  # a list: see check_shape
    if len(shape) != 2 or shape[1] < 3:
        raise ParameterError(
            f"must have shape (N, C>=3) with x, y, z first, got {shape}", param=name
        )
    check_dtype(a, name, "fiu")
    if nonempty and shape[0] == 0:
        raise ParameterError("has no points", param=name)
    return int(shape[1])


# -- text syntaxes -------------------------------------------------------------------------------

_NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_SIZE = re.compile(rf"^\s*({_NUMBER})\s*[xX]\s*({_NUMBER})\s*$")
_CROP = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*\+\s*(\d+)\s*\+\s*(\d+)\s*$")
_LEGACY_CROP = re.compile(r"^\s*-?\d+\s*,\s*-?\d+\s*,\s*-?\d+\s*,\s*-?\d+\s*$")


def parse_size(text, name: str = "image_size", *, integer: bool = True) -> tuple:
    """``"1242x375"`` -> ``(1242, 375)``: width and height, both > 0 (and finite).

    With ``integer=False`` the sizes may be real numbers (a window in metres: ``2.35x2.35``).
    """
    if isinstance(text, (tuple, list)) and len(text) == 2:
        text = f"{text[0]}x{text[1]}"
    m = _SIZE.match(str(text))
    example = "1242x375" if integer else "2.35x2.35"
    if not m:
        raise ParameterError(f"expected WxH such as {example}, got {text!r}", param=name)
    try:
        w, h = (int(v) for v in m.groups()) if integer else (float(v) for v in m.groups())
    except ValueError:
        raise ParameterError(f"expected whole numbers WxH such as {example}, got {text!r}",
                             param=name) from None  # fmt: skip
    if not (math.isfinite(w) and math.isfinite(h)) or w <= 0 or h <= 0:
        raise ParameterError(f"width and height must be finite and > 0, got {text!r}", param=name)
    return w, h


def is_legacy_crop(text) -> bool:
    """True for the pre-0.3 crop syntax ``TOP,LEFT,H,W`` (still read, with a warning)."""
    return isinstance(text, str) and bool(_LEGACY_CROP.match(text))


def parse_crop(value, name: str = "crop") -> tuple[int, int, int, int]:
    """A crop box as ``(top, left, height, width)`` pixels.

    Reads ``"WxH+LEFT+TOP"`` (``"800x350+0+100"``: 800 wide, 350 high, from column 0, row
    100), the pre-0.3 text ``"TOP,LEFT,H,W"`` (``"100,0,350,800"``), or a 4-sequence
    ``(top, left, height, width)``. TOP, LEFT >= 0 and H, W > 0.
    """
    if isinstance(value, str):
        m = _CROP.match(value)
        if m:
            w, h, left, top = (int(v) for v in m.groups())
            parts = (top, left, h, w)
        elif _LEGACY_CROP.match(value):
            parts = tuple(int(v) for v in value.split(","))
        else:
            raise ParameterError(
                f"expected {CROP_SYNTAX} such as 800x350+0+100, got {value!r}", param=name
            )
    else:
        try:
            parts = tuple(int(v) for v in value)
        except (TypeError, ValueError):
            raise ParameterError(f"expected {CROP_SYNTAX}, got {value!r}", param=name) from None
        if len(parts) != 4:
            raise ParameterError(f"expected (top, left, height, width), got {value!r}", param=name)
    top, left, h, w = parts
    if top < 0 or left < 0 or h <= 0 or w <= 0:
        raise ParameterError(f"TOP, LEFT must be >= 0 and W, H > 0, got {value!r}", param=name)
    return parts


def format_crop(crop: Sequence[int]) -> str:
    """``(top, left, height, width)`` -> ``"WxH+LEFT+TOP"``."""
    top, left, h, w = (int(v) for v in crop)
    return f"{w}x{h}+{left}+{top}"


def parse_pair(
    text,
    name: str,
    *,
    integer: bool = False,
    single: bool = True,
    low: float | None = None,
    strict: bool = False,
    high: float | None = None,
) -> tuple:
    """``"A,B"`` (or ``"V"`` for ``(V, V)`` when ``single``) -> an ordered pair of finite
    numbers, checked by :func:`check_pair`."""
    parts = [p.strip() for p in str(text).split(",")]
    kind = "integers" if integer else "numbers"
    try:
        values = [int(p) if integer else float(p) for p in parts]
    except ValueError:
        form = "V or LOW,HIGH" if single else "A,B"
        raise ParameterError(f"expected {form} as {kind}, got {text!r}", param=name) from None
    if len(values) == 1 and single:
        values = values * 2
    if len(values) != 2:
        form = "V or LOW,HIGH" if single else "two numbers as A,B"
        raise ParameterError(f"expected {form}, got {text!r}", param=name)
    return check_pair(values, name, low=low, high=high, strict=strict, integer=integer)


def parse_int_list(value, name: str, *, low: int | None = None, unique: bool = False) -> tuple:
    """``"5,7,9,11"`` (or several values, or ``"5 7 9"``) -> a tuple of ints."""
    items = value if isinstance(value, (tuple, list)) else (value,)
    out: list[int] = []
    try:
        for item in items:
            out.extend(int(v) for v in str(item).replace(",", " ").split())
    except ValueError:
        raise ParameterError(f"expected integers, got {value!r}", param=name) from None
    if low is not None and any(v < low for v in out):
        raise ParameterError(f"values must be >= {low}, got {value!r}", param=name)
    if unique and len(set(out)) != len(out):
        raise ParameterError(f"values repeat: {value!r}", param=name)
    return tuple(out)


def parse_frame_range(text, name: str = "frame_range") -> tuple[int | None, int | None, int]:
    """``"FROM:TO[:STEP]"`` (Python slice syntax over a sorted list, each part optional:
    ``"10:20"``, ``":100"``, ``"::10"``, ``"-5:"``) -> ``(start, stop, step)``.

    ``start`` and ``stop`` are positions (None: from the first / to the end; negative: from
    the end), ``step`` >= 1. ``""`` selects everything: ``(None, None, 1)``.
    """
    text = "" if text is None else str(text).strip()
    if not text:
        return None, None, 1
    parts = [p.strip() for p in text.split(":")]
    if len(parts) not in (2, 3):
        raise ParameterError(
            f"expected FROM:TO or FROM:TO:STEP such as 0:100:5, got {text!r}", param=name
        )
    try:
        values = [int(p) if p else None for p in parts]
    except ValueError:
        raise ParameterError(
            f"expected whole numbers in FROM:TO[:STEP], got {text!r}", param=name
        ) from None
    start, stop = values[0], values[1]
    step = values[2] if len(values) == 3 and values[2] is not None else 1
    if step < 1:
        raise ParameterError(f"the step must be >= 1, got {text!r}", param=name)
    return start, stop, step
