"""``dataset export --layout monodepth2-gt``: the ``gt_depths.npz`` monodepth2 evaluates with.

monodepth2's ``evaluate_depth.py`` reads one NumPy archive, ``splits/<split>/gt_depths.npz``::

    gt_depths = np.load(gt_path, fix_imports=True, encoding="latin1", allow_pickle=True)["data"]

an object array holding one float32 (H, W) depth map in metres per line of the split's
``test_files.txt``, in the order of its lines, at the raw image size of the line's drive
(``S_rect_02``: 1242x375, 1224x370, ...), 0 = no value. :func:`export_monodepth2_gt` writes
it from a KITTI raw tree as monodepth2's ``export_gt_depth.py --split eigen`` does: each
line's Velodyne scan projected into camera 2 (:func:`~sparsetools.ops.eigen_gt.eigen_depth_map`:
points with x < 0 dropped, -1 px offset, the nearest value per pixel) storing the point's
**Velodyne x**, not its camera z, as ``generate_depth_map(..., vel_depth=True)`` does. Like
monodepth2, the line's ``l`` / ``r`` is not used: the map is always camera 2's.

A line whose drive or scan is not in the tree makes the export refuse, naming the count and
the first such lines: monodepth2 pairs maps and predictions by position, so a skipped line
would shift every later map. The archive is written to a temporary file in the output folder
and renamed; a rerun with the same split file, tree and settings is a no-op, another export
in its place is refused unless ``overwrite`` (:class:`~.output_file.OutputFile`).
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..ops.eigen_gt import VALUES, eigen_depth_map
from ..validate import check_choice
from .core import check_output_dir

__all__ = ["GT_FILE", "Monodepth2GtSettings", "export_monodepth2_gt"]

GT_FILE = "gt_depths.npz"
#: Lines named in the message refusing missing ones.
_SHOWN = 3


@dataclass(frozen=True)
class Monodepth2GtSettings:
    """What makes the archive (recorded with it, compared on a rerun)."""

    root: str = field(default="", metadata={"option": "MAPS"})
    split_file: str = field(default="", metadata={"option": "--split-file"})
    value: str = field(default="velodyne-x", metadata={"option": "--depth-value"})

    def __post_init__(self) -> None:
        check_choice(self.value, "depth_value", VALUES)


def _scans(root: Path, lines: list[tuple[str, ...]], split_file: Path) -> list[tuple[Path, Path]]:
    """(scan, calibration folder) of every line, or a ParameterError naming the missing."""
    from ..io.sources import kitti_raw_drives

    drives = {d.name: (d, c) for d, c in kitti_raw_drives(root)}
    if not drives:
        raise ParameterError(f"{root}: not a KITTI raw drive, date folder or root", param="MAPS")
    found, missing = [], []
    for parts in lines:
        if len(parts) < 2:
            raise ParameterError(
                f"{split_file}: '{parts[0]}' is not a KITTI split line ('<date>/<drive> <frame> "
                "[l|r]', as monodepth2's test_files.txt)",
                param="--split-file",
            )
        drive, calib = drives.get(parts[0].rstrip("/").rpartition("/")[2], (None, None))
        scan = None
        if drive is not None and calib is not None:
            scan = drive / "velodyne_points" / "data" / f"{int(parts[1]):010d}.bin"
        if scan is None or not scan.is_file():
            missing.append(" ".join(parts))
        else:
            found.append((scan, calib))
    if missing:
        more = f", ... {len(missing) - _SHOWN} more" if len(missing) > _SHOWN else ""
        raise ParameterError(
            f"{len(missing)} of the {len(lines)} lines of {split_file} have no Velodyne scan "
            f"(or no calibration) in {root}: {', '.join(missing[:_SHOWN])}{more}; monodepth2 "
            "pairs maps with predictions by line, so every line needs its scan (give a split "
            "file of the lines present)",
            param="--split-file",
        )
    return found


def export_monodepth2_gt(
    root: str | os.PathLike,
    split_file: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    value: str = "velodyne-x",
    overwrite: bool = False,
    progress: bool = False,
) -> dict:
    """Write ``OUT/gt_depths.npz`` for monodepth2's ``evaluate_depth.py``.

    Parameters
    ----------
    root : path-like
        A KITTI raw root of dates, date folder or drive (``velodyne_points/data/*.bin`` and
        the date's ``calib_cam_to_cam.txt`` / ``calib_velo_to_cam.txt``).
    split_file : path-like
        monodepth2's ``test_files.txt`` form: ``<date>/<drive> <frame> [l|r]`` per line.
    out_dir : path-like
        Output folder (created; not inside ``root``).
    value : {'velodyne-x', 'camera-z'}
        What a pixel holds: monodepth2's Velodyne x (default), or the camera z.
    overwrite : bool
        Replace an archive written otherwise (or not by sparsetools).
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    dict
        ``lines``, ``maps`` written (0 when up to date), ``sizes`` (``WxH`` -> count),
        ``density`` (mean share of pixels with a value), ``value``, ``output``.

    Raises
    ------
    ParameterError
        Split lines without their scan (the count and the first lines), a line not in the
        KITTI form, an empty split file.
    """
    from ..io.atomic import atomic_path
    from ..io.calib import read_kitti_raw_calib
    from ..io.kitti import read_velodyne_bin
    from .dataset.splits import read_split_file
    from .output_file import OutputFile

    root, split_file = Path(root), Path(split_file)
    settings = Monodepth2GtSettings(str(root.resolve()), str(split_file.resolve()), value)
    lines = read_split_file(split_file)
    if not lines:
        raise ParameterError(f"{split_file}: no split lines", param="--split-file")
    scans = _scans(root, lines, split_file)
    out = check_output_dir(out_dir, [root])
    target = out / GT_FILE
    calibs = sorted({c for _, c in scans})
    sources = [split_file, *(c / n for c in calibs for n in ("calib_cam_to_cam.txt",
                                                            "calib_velo_to_cam.txt")),
               *(s for s, _ in scans)]  # fmt: skip
    record = OutputFile(target, "export", settings, sources, overwrite=overwrite,
                        noun="a monodepth2 ground truth")  # fmt: skip
    if record.up_to_date():
        return {"lines": len(lines), "maps": 0, "up_to_date": True, "value": value,
                "output": str(target)}  # fmt: skip
    cams = {c: read_kitti_raw_calib(c, camera=2) for c in calibs}
    maps = np.empty(len(scans), dtype=object)
    sizes: Counter = Counter()
    density = 0.0
    from tqdm import tqdm

    with tqdm(total=len(scans), desc="monodepth2-gt", unit="scan", disable=not progress,
              leave=False) as bar:  # fmt: skip
        for i, (scan, calib_dir) in enumerate(scans):
            cal = cams[calib_dir]
            depth = eigen_depth_map(read_velodyne_bin(scan), cal.projection,
                                    (cal.height, cal.width), value=value)  # fmt: skip
            maps[i] = depth
            sizes[f"{cal.width}x{cal.height}"] += 1
            density += float(np.count_nonzero(depth)) / depth.size
            bar.update(1)
    with atomic_path(target, overwrite=True) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, data=maps)  # a file object: no ".npz" appended to the name
    record.record()
    return {"lines": len(lines), "maps": len(scans), "sizes": dict(sizes),
            "density": round(density / len(scans), 5), "value": value,
            "output": str(target)}  # fmt: skip
