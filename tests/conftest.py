"""Shared fixtures: the real KITTI / nuScenes samples beside the checkout, when present."""

from __future__ import annotations

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
