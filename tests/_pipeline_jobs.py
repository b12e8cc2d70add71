"""Module-level per-frame jobs for the pipeline tests (must be picklable)."""

from __future__ import annotations

import os
from dataclasses import dataclass

from sparsetools.errors import FormatError
from sparsetools.io.atomic import atomic_path
from sparsetools.random import frame_rng


@dataclass(frozen=True)
class RandomInput:
    """A frame's input: an optional file whose bytes are mixed into the output."""

    source: str | None = None


@dataclass(frozen=True)
class WriteRandom:
    """Writes 16 random doubles from frame_rng(seed, frame id) (plus the input's bytes)."""

    seed: int = 7
    bad: tuple[str, ...] = ()

    def __call__(self, task):
        rng = frame_rng(self.seed, task.frame_id)
        if task.frame_id in self.bad:
            raise FormatError(f"{task.frame_id}.bin: truncated")
        values = rng.random(16)
        extra = b""
        if task.inputs is not None and task.inputs.source:
            with open(task.inputs.source, "rb") as fh:
                extra = fh.read()
        with atomic_path(task.outputs["data"]) as tmp:
            tmp.write_bytes(values.tobytes() + extra)
        return {"sum": float(values.sum()), "pid": os.getpid()}


def crash(task):
    raise ZeroDivisionError("bug")


@dataclass(frozen=True)
class ChangeInput:
    """Writes its output and (``change``) appends to its input file while it runs, as another
    program writing the input at the same moment would."""

    change: bool = True

    def __call__(self, task):
        with atomic_path(task.outputs["data"]) as tmp:
            tmp.write_bytes(b"output")
        if self.change:
            with open(task.inputs.source, "ab") as fh:
                fh.write(b"+")
        return {}
