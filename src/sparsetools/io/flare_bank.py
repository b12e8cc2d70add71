"""An on-disk copy of a flare bank (``.npz``): built once, then loaded by every process.

The file holds exactly the in-memory arrays of :func:`sparsetools.ops.flare.build_flare_bank`,
so results do not depend on whether the copy was used. A file that cannot be read, or that
does not match its name, is rebuilt (a cache never fails a run).
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from ..errors import SparsetoolsError
from ..ops.flare import BANK_VERSION, FlareBank, build_flare_bank
from .atomic import atomic_path

__all__ = ["cached_flare_bank"]

log = logging.getLogger(__name__)


def _bank_file(cache_dir: Path, seed: int, count: int, size: int) -> Path:
    return cache_dir / f"flare-bank-v{BANK_VERSION}-s{seed}-n{count}-p{size}.npz"


def _load_bank(path: Path, seed: int, count: int, size: int) -> FlareBank | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            patterns = z["patterns"]
            ghost_arr = z["ghosts"]
            desc = tuple(str(s) for s in z["descriptions"])
            meta = z["meta"]
    except Exception as exc:  # a corrupt zip/npy raises many types; a cache is just rebuilt
        log.warning("ignoring unreadable flare bank cache %s (%s); rebuilding it", path, exc)
        return None
    if (
        meta.shape != (4,)
        or meta.dtype.kind not in "iu"
        or tuple(int(v) for v in meta) != (BANK_VERSION, seed, count, size)
        or patterns.shape != (count, size, size, 3)
        or patterns.dtype != np.float32
        or ghost_arr.ndim != 3
        or ghost_arr.dtype.kind != "f"
        or ghost_arr.shape[0] < 1
        or len(desc) != count
    ):
        log.warning("flare bank cache %s does not match its name; rebuilding it", path)
        return None
    return FlareBank(seed, size, patterns, ghost_arr.astype(np.float32), desc)


def _save_bank(path: Path, bank: FlareBank) -> None:
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                patterns=bank.patterns,
                ghosts=bank.ghosts,
                descriptions=np.array(bank.descriptions),
                meta=np.array([BANK_VERSION, bank.seed, bank.count, bank.size], np.int64),
            )
    except (OSError, SparsetoolsError) as exc:  # a cache only saves time: never fail for it
        log.warning("cannot write flare bank cache %s: %s", path, exc)


@functools.lru_cache(maxsize=8)
def _cached(seed: int, count: int, size: int, cache_dir: str) -> FlareBank:
    path = _bank_file(Path(cache_dir), seed, count, size)
    bank = _load_bank(path, seed, count, size) if path.is_file() else None
    if bank is None:
        bank = build_flare_bank(seed=seed, count=count, size=size)
        _save_bank(path, bank)
    bank.patterns.setflags(write=False)
    bank.ghosts.setflags(write=False)
    return bank


def cached_flare_bank(
    cache_dir: str | os.PathLike, *, seed: int = 0, count: int = 16, size: int = 256
) -> FlareBank:
    """The flare bank for (seed, count, size), from ``cache_dir`` when a copy is there
    (written atomically otherwise); read-only arrays, one object per process and key."""
    return _cached(int(seed), int(count), int(size), str(Path(cache_dir)))
