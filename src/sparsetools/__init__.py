"""sparsetools: camera + sparse depth sensor data to depth-estimation datasets.

The public API lives at the top level and is imported lazily, so ``import sparsetools`` is
fast and pulls in neither numba, Open3D nor torch::

    import sparsetools as st
    points = st.read_points("000000.bin")               # (N, 4) float32
    calib = st.load_calibration("calib/000000.txt").with_size(1242, 375)
    depth = st.project_points(points, calib)            # (375, 1242) float32 metres
    st.write_depth_png("000000.png", depth)
"""

from __future__ import annotations

import importlib

from ._version import __version__
from .errors import SparsetoolsError

# name -> module (relative to this package) that defines it
_LAZY = {
    "Calibration": ".calibration",
    "read_points": ".io.pointcloud",
    "write_points": ".io.pointcloud",
    "load_calibration": ".io.calib",
    "read_depth_png": ".io.image",
    "write_depth_png": ".io.image",
    "read_image": ".io.image",
    "write_image": ".io.image",
    "read_radar_pcd": ".io.nuscenes",
    "write_radar_pcd": ".io.nuscenes",
    "frame_rng": ".random",
    "project_points": ".ops.projection",
    "project_points_with_index": ".ops.projection",
    "accumulate_sweeps": ".ops.projection",
    "recover_rings": ".ops.rings",
    "select_beams": ".ops.beams",
    "ring_table": ".ops.rings",
    "load_sensor_profile": ".io.sensor_profile",
    "dense_to_sparse": ".ops.sparse",
    "sparse_to_dense": ".ops.sparse",
    "DatasetReader": ".io.dataset_reader",
    "build_dataset": ".pipeline.dataset",
    "verify_dataset": ".pipeline.dataset",
    "depth_stats": ".ops.stats",
    "jbf_expand": ".ops.jbf",
    "height_extend": ".ops.jbf",
    "intrinsic_error": ".ops.intrinsic",
    "depth_metrics": ".ops.metrics",
    "lowlight": ".ops.lowlight",
    "LowLightParams": ".ops.lowlight",
    "LowLightRecord": ".ops.lowlight",
    "flare_bank": ".ops.flare",
    "mcie_lut": ".ops.enhance",
    "apply_lut": ".ops.enhance",
    "UnderwaterCompensator": ".ops.underwater",
    "median_failure_probability": ".ops.underwater",
    "run_frames": ".pipeline",
    "run_job": ".pipeline",
}

__all__ = ["SparsetoolsError", "__version__", *sorted(_LAZY)]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'sparsetools' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
