"""Shared fixtures: the real KITTI / nuScenes samples beside the checkout, when present."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

#: ../shared/data/real relative to the repository root (CI clones with shared/ beside it).
REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
SAMPLE_DATA = Path(__file__).resolve().parent.parent / "sample_data"


@pytest.fixture(scope="session")
def real_dir() -> Path:
    if not REAL.is_dir():
        pytest.skip(f"real sample data not present at {REAL}")
    return REAL


@pytest.fixture(scope="session")
def kitti_object(real_dir) -> Path:
    return real_dir / "kitti-object-kuixu"


@pytest.fixture(scope="session")
def nuscenes_demo(real_dir) -> Path:
    return real_dir / "nuscenes-mmdet3d-demo"


@pytest.fixture(autouse=True)
def _restore_root_logger():
    """CLI invocations configure the root logger (``--quiet`` raises it to ERROR,
    ``basicConfig(force=True)`` replaces its handlers); undo that after every test so a later
    test's ``caplog`` sees warnings whatever ran before it."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers
