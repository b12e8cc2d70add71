"""Sensor profiles on disk: the built-in ``hdl64e-kitti`` profile or a user's JSON file."""

from __future__ import annotations

import json
import os
from pathlib import Path

from ..errors import FormatError
from ..ops.lidar_profile import SensorProfile

__all__ = ["BUILTIN_PROFILES", "load_sensor_profile"]

_PROFILE_DIR = Path(__file__).resolve().parent.parent / "data"
#: Built-in profile name -> file in the package's data folder.
BUILTIN_PROFILES = {"hdl64e-kitti": "hdl64e_kitti.json"}
_BUILTIN_PROFILES = BUILTIN_PROFILES


def load_sensor_profile(name_or_path: str | os.PathLike) -> SensorProfile:
    """A built-in profile by name (``hdl64e-kitti``) or a profile JSON file.

    Raises
    ------
    FormatError
        Unknown name, unreadable file or missing keys.
    """
    key = str(name_or_path)
    path = _PROFILE_DIR / _BUILTIN_PROFILES[key] if key in _BUILTIN_PROFILES else Path(key)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        known = ", ".join(sorted(_BUILTIN_PROFILES))
        raise FormatError(
            f"{key}: no such sensor profile (built-in: {known}, or a JSON file)"
        ) from exc
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: cannot read the sensor profile ({exc})") from exc
    try:
        main = {k: data[k] for k in ("name", "elevation_deg", "beam_angle_deg", "z_offset_m")}
    except (KeyError, TypeError) as exc:
        raise FormatError(f"{path}: sensor profile lacks key {exc}") from exc
    extra = {
        k: v
        for k, v in data.items()
        if k not in (*main, "n_lasers", "ring_order", "far_range_m", "reference_range_m", "source")
    }
    try:
        return SensorProfile(
            **main,
            far_range_m=float(data.get("far_range_m", 20.0)),
            reference_range_m=float(data.get("reference_range_m", 30.0)),
            source=str(data.get("source", "")),
            extra=extra,
        )
    except FormatError:
        raise
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{path}: sensor profile values are not numbers ({exc})") from exc
