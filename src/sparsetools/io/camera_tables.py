"""ELD-style camera noise tables from a JSON file of one's own calibrations.

The format is that of the shipped ``sparsetools/data/eld_cameras.json`` (ELD's released tables,
Wei et al. CVPR 2020, MIT): ``{"cameras": {NAME: {"Kmin", "Kmax", "G_shape", "color_bias",
"Profile-1": {"G_scale", "g_scale", "R_scale"}, "saturation_dn"}}}``. The profiles it returns go
straight to :func:`sparsetools.ops.noise.sample_noise_params` as ``camera=``; the built-in
tables need no reader (``sparsetools.ops.noise.CAMERA_PROFILES``). Pickled ``.npy`` tables are
never read: convert them to JSON with a restricted unpickler first.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import FormatError
from ..ops.noise import CameraProfile

__all__ = ["read_camera_tables"]


def read_camera_tables(path: str | os.PathLike) -> dict[str, CameraProfile]:
    """Camera noise profiles of a tables file, by name.

    Parameters
    ----------
    path : path-like
        JSON file in the format of ``sparsetools/data/eld_cameras.json``.

    Returns
    -------
    dict of str to CameraProfile
        In name order.

    Raises
    ------
    FormatError
        Unreadable file, not JSON, no ``cameras`` object, or a camera entry with missing or
        non-finite values (the message names the file and the camera).
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FormatError(f"{p}: no such camera tables file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"{p}: cannot read the camera tables ({exc})") from exc
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(cams, dict) or not cams:
        raise FormatError(f"{p}: expected a JSON object with a non-empty 'cameras' object")
    out = {}
    for name in sorted(cams):
        if not isinstance(cams[name], dict):
            raise FormatError(f"{p}: camera '{name}' is not a JSON object")
        try:
            out[name] = CameraProfile.from_dict(name, cams[name])
        except FormatError as exc:
            raise FormatError(f"{p}: {exc}") from exc
    return out
