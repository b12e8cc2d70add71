"""Source adapters: which frames a batch has, and each frame's files.

Every batch command enumerates its inputs here, as :class:`Frame` records keyed by
``(sequence, frame)`` (:class:`FrameKey`):

- :func:`index_input` turns one path given for a role (``cloud``, ``image``, ``sparse``,
  ``gt``, ``depth``, ``confidence``, ``calib``) into a :class:`FileIndex`, recognising the
  layout: a file, a folder tree (``DIR/<sequence>/<frame>.ext``), a folder written by
  sparsetools (read through its record), a KITTI raw drive / date folder / root of dates, a
  KITTI object split, a KITTI depth-completion tree, a ``val_selection_cropped`` folder, a
  ``synth-scene --video`` folder (with its poses);
- :func:`cloud_frames` builds the frames of point-cloud commands (``project``, ``beams``)
  from clouds plus an optional calibration and image (shared, or per frame by key), and
  :func:`cloud_source` the frames of exactly one source (clouds, KITTI raw, KITTI object,
  nuScenes) with their calibration;
- :func:`image_frames` / :func:`images_with_depth` the frames of image commands,
  :func:`depth_frames` of depth-map commands, :func:`radar_frames` of ``jbf-expand``;
- :func:`nuscenes_frames` builds frames from nuScenes tables;
- :func:`match_keys` matches the files of another input to frames by key.

Nothing here reads a cloud or an image, so a bad frame fails in its own job (and
``--on-error skip`` can skip it).
"""

from __future__ import annotations

from .clouds import CloudSource, cloud_frames, cloud_source
from .depth import RADAR_SUFFIXES, depth_frames, radar_frames
from .frame import Frame, FrameKey, Sweep, check_key_part
from .images import image_frames, images_with_depth
from .index import ROLES, attach, index_input, is_shared_calibration, merge_frames
from .kitti import (
    is_kitti_raw,
    is_kitti_raw_calib_dir,
    kitti_object_index,
    kitti_raw_drives,
    kitti_raw_index,
)
from .nuscenes import nuscenes_frames
from .tree import (
    CALIB_SUFFIXES,
    CLOUD_SUFFIXES,
    DEPTH_SUFFIXES,
    IMAGE_SUFFIXES,
    FileIndex,
    file_stem,
    index_tree,
    match_keys,
)

__all__ = [
    "CALIB_SUFFIXES",
    "CLOUD_SUFFIXES",
    "DEPTH_SUFFIXES",
    "IMAGE_SUFFIXES",
    "RADAR_SUFFIXES",
    "ROLES",
    "CloudSource",
    "FileIndex",
    "Frame",
    "FrameKey",
    "Sweep",
    "attach",
    "check_key_part",
    "cloud_frames",
    "cloud_source",
    "depth_frames",
    "file_stem",
    "image_frames",
    "images_with_depth",
    "index_input",
    "index_tree",
    "is_kitti_raw",
    "is_kitti_raw_calib_dir",
    "is_shared_calibration",
    "kitti_object_index",
    "kitti_raw_drives",
    "kitti_raw_index",
    "match_keys",
    "merge_frames",
    "nuscenes_frames",
    "radar_frames",
]
