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
    "UsageError",
]


class SparsetoolsError(Exception):
    """Base class of every error that sparsetools raises on purpose."""


class FormatError(SparsetoolsError, ValueError):
    """A file is missing, unreadable, truncated or not in the expected format."""


class CalibrationError(FormatError):
    """A calibration is missing a key, holds non-numeric values or a singular matrix."""


class ParameterError(SparsetoolsError, ValueError):
    """An argument is outside its valid range or inconsistent with another one.

    Parameters
    ----------
    message : str
    param : str, optional
        The parameter's name as the library spells it (``"max_depth"``) or as an option
        (``"--max-depth"``); ``str(error)`` names it as the option
        (``--max-depth: must be > 0``), ``error.message`` is the message alone.
    """

    def __init__(self, message: str, *, param: str | None = None):
        super().__init__(message)
        self.message = message
        self.param = param

    def __str__(self) -> str:
        opt = self.option
        if opt and not self.message.startswith(opt):
            return f"{opt}: {self.message}"
        return self.message

    @property
    def option(self) -> str | None:
        """``--max-depth`` for ``param="max_depth"`` (None without a parameter)."""
        if not self.param:
            return None
        return self.param if self.param.startswith("-") else "--" + self.param.replace("_", "-")


class UsageError(ParameterError):
    """Options that do not go together, or one that is missing: the command line exits with
    code 2, as for its own usage errors."""


class OutputError(SparsetoolsError):
    """An output cannot be written: exists, not writable, or inside an input."""


class DependencyError(SparsetoolsError, ImportError):
    """An optional dependency (Open3D, torch, dask) or its system library is missing."""


class FrameError(SparsetoolsError):
    """One or more frames of a batch failed (raised after the batch with ``on_error='skip'``)."""
