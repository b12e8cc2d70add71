"""Module-level per-frame functions for the pipeline tests (must be picklable)."""

from __future__ import annotations

from sparsetools.errors import FormatError
from sparsetools.io.atomic import atomic_path
from sparsetools.random import frame_rng


def write_random(task):
    rng = frame_rng(task.inputs["seed"], task.frame_id)
    if task.frame_id in task.inputs.get("bad", ()):
        raise FormatError(f"{task.frame_id}.bin: truncated")
    values = rng.random(16)
    with atomic_path(task.outputs[0]) as tmp:
        tmp.write_bytes(values.tobytes())
    return {"sum": float(values.sum())}


def crash(task):
    raise ZeroDivisionError("bug")
