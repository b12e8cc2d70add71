"""Per-frame random generators that do not depend on worker count or frame order."""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["frame_rng", "frame_seed"]


def frame_seed(seed: int, frame_id: str | int) -> np.random.SeedSequence:
    """SeedSequence derived from the global ``seed`` and a frame identifier.

    The frame id is hashed (SHA-256, stable across processes and Python versions, unlike
    ``hash()``), so the same (seed, frame) pair always gives the same stream.
    """
    digest = hashlib.sha256(str(frame_id).encode("utf-8")).digest()
    words = np.frombuffer(digest[:16], dtype="<u4").tolist()
    return np.random.SeedSequence([int(seed) & 0xFFFFFFFF, *words])


def frame_rng(seed: int, frame_id: str | int) -> np.random.Generator:
    """``numpy.random.Generator`` for one frame (see :func:`frame_seed`)."""
    return np.random.default_rng(frame_seed(seed, frame_id))
