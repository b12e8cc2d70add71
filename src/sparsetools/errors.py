"""Exceptions raised by sparsetools.

The library raises these and nothing click-specific; the command line maps every
:class:`SparsetoolsError` to a one-line message on stderr and exit code 1.
"""

from __future__ import annotations

__all__ = [
    "CalibrationError",
    "DependencyError",
    "FormatError",
    "FrameError",
    "OutputError",
    "ParameterError",
    "SparsetoolsError",
]


class SparsetoolsError(Exception):
    """Base class of every error that sparsetools raises on purpose."""


class FormatError(SparsetoolsError, ValueError):
    """A file is missing, unreadable, truncated or not in the expected format."""


class CalibrationError(FormatError):
    """A calibration is missing a key, holds non-numeric values or a singular matrix."""


class ParameterError(SparsetoolsError, ValueError):
    """An argument is outside its valid range or inconsistent with another one."""


class OutputError(SparsetoolsError):
    """An output cannot be written: exists, not writable, or inside an input."""


class DependencyError(SparsetoolsError, ImportError):
    """An optional dependency (Open3D, torch, dask) or its system library is missing."""


class FrameError(SparsetoolsError):
    """One or more frames of a batch failed (raised after the batch with ``on_error='skip'``)."""
