"""A one-line error instead of ``ModuleNotFoundError`` where PyTorch is not installed.

``pip install sparsetools`` leaves torch out; the ``train`` extra brings it. The commands that
need it (``train``, ``eval --checkpoint``) call :func:`require_torch` before importing any
torch module of this package. This module imports nothing of torch itself.
"""

from __future__ import annotations

import importlib

from ..errors import DependencyError

__all__ = ["INSTALL_HINT", "require_torch"]

#: How to get torch (the extra of pyproject.toml).
INSTALL_HINT = "pip install 'sparsetools[train]'"


def require_torch(what: str) -> None:
    """Import torch, or raise :class:`DependencyError` naming ``what`` needs it.

    Parameters
    ----------
    what : str
        The command or option that needs torch, e.g. ``"train"``, ``"eval --checkpoint"``.

    Raises
    ------
    DependencyError
        torch is not installed (``Error: train needs PyTorch: pip install
        'sparsetools[train]'``), or is installed but cannot be imported (its message added).
    """
    try:
        importlib.import_module("torch")
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] != "torch":
            raise DependencyError(
                f"{what} needs PyTorch, which cannot be imported (no module {exc.name!r}): "
                f"{INSTALL_HINT}"
            ) from exc
        raise DependencyError(f"{what} needs PyTorch: {INSTALL_HINT}") from exc
    except (ImportError, OSError) as exc:  # a broken install: a missing shared library
        detail = " ".join(str(exc).split())[:200]
        raise DependencyError(
            f"{what} needs PyTorch, which cannot be imported ({detail}): {INSTALL_HINT}"
        ) from exc
