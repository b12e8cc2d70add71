"""Record sidecars: the JSON object written beside each output of ``lowlight-synth`` and
``defocus-synth`` (``OUT/records/<sequence>/<frame>.json``), read back to rebuild their
manifests."""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import FormatError

__all__ = ["MAX_SIDECAR_BYTES", "read_sidecar"]

#: Largest sidecar read (bytes): a real one is a few KiB.
MAX_SIDECAR_BYTES = 1 << 20


def read_sidecar(path: str | os.PathLike) -> dict:
    """The JSON object of a record sidecar.

    Raises
    ------
    FormatError
        Unreadable, larger than :data:`MAX_SIDECAR_BYTES`, not JSON, or not an object.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_SIDECAR_BYTES:
            raise FormatError(
                f"{path}: {size} bytes is not a record sidecar (at most {MAX_SIDECAR_BYTES}); "
                "rerun with --overwrite"
            )
        side = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        why = "nested too deeply" if isinstance(exc, RecursionError) else exc
        raise FormatError(
            f"{path}: unreadable record sidecar ({why}); rerun with --overwrite"
        ) from exc
    if not isinstance(side, dict):
        raise FormatError(f"{path}: not a record sidecar (a JSON object); rerun with --overwrite")
    return side
