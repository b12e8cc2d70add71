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


#: The root logger's level when the session started: a module- or session-scoped fixture that
#: runs a command with ``-q`` sets it to ERROR before any test's own set-up sees it.
_ROOT_LEVEL = logging.getLogger().level


@pytest.fixture(autouse=True)
def _restore_root_logger():
    """CLI invocations configure the root logger (``--quiet`` raises it to ERROR,
    ``basicConfig(force=True)`` replaces its handlers); undo that around every test so a
    test's ``caplog`` sees warnings whatever ran before it (fixtures included)."""
    root = logging.getLogger()
    handlers = list(root.handlers)
    root.setLevel(_ROOT_LEVEL)
    yield
    root.setLevel(_ROOT_LEVEL)
    root.handlers[:] = handlers
