"""A tiny analytic street for self-supervised tests: renderer, video sequences, dataset writer.

The scene (world frame = the first camera; x right, y down, z forward): a ground plane at
y = +1.5 m, two building walls at x = -6 m and x = +6 m, and a back wall at z = 60 m, each with
a smooth procedural colour texture (sums of sinusoids of the world coordinates, so bilinear
interpolation of a rendering is accurate). Rays that hit nothing are sky (depth 0). An optional
"moving object" is a square patch glued to the image (it moves with the camera).

Other test modules import :func:`render`, :func:`video` and :func:`write_video_dataset`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

GROUND_Y = 1.5
WALL_X = 6.0
BACK_Z = 60.0
SKY = np.array([0.55, 0.7, 0.9])


def intrinsics(h: int, w: int) -> np.ndarray:
    f = 0.58 * w * 1.3
    return np.array([[f, 0, (w - 1) / 2], [0, f, 0.42 * (h - 1)], [0, 0, 1]], np.float64)


def _texture(a: np.ndarray, b: np.ndarray, phase: float) -> np.ndarray:
    """(N,) x (N,) world coordinates -> (N, 3) colours in [0.1, 0.9]."""
    out = []
    for c in range(3):
        p = phase + 1.7 * c
        v = (
            0.5
            + 0.2 * np.sin(0.65 * a + 0.35 * b + p)
            + 0.12 * np.sin(0.2 * a - 0.95 * b + 2 * p)
            + 0.06 * np.sin(1.15 * a + 1.45 * b - p)
        )
        out.append(v)
    return np.stack(out, axis=-1)


def render(
    K: np.ndarray,
    T_world_cam: np.ndarray,
    h: int,
    w: int,
    *,
    patch: bool = False,
    labels: bool = False,
):
    """Colour (H, W, 3) float64 in [0, 1] and depth (H, W) float64 metres (0 = sky).

    With ``labels`` also the (H, W) int surface of each pixel: -1 sky, 0 ground, 1 left wall,
    2 right wall, 3 back wall, 4 the patch (texture seams lie between different labels).
    """
    v, u = np.meshgrid(
        np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij"
    )
    rays_cam = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    rays_cam = np.linalg.inv(K) @ rays_cam  # z = 1: the ray parameter is camera depth
    R, C = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d = R @ rays_cam  # world directions
    best = np.full(u.size, np.inf)
    colour = np.tile(SKY, (u.size, 1))
    surface = np.full(u.size, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = [
            ((GROUND_Y - C[1]) / d[1], 0, 2, 0.0),  # ground: texture of (x, z)
            ((-WALL_X - C[0]) / d[0], 1, 2, 1.0),  # left wall: (y, z)
            ((WALL_X - C[0]) / d[0], 1, 2, 2.0),  # right wall: (y, z)
            ((BACK_Z - C[2]) / d[2], 0, 1, 3.0),  # back wall: (x, y)
        ]
    for label, (s, ia, ib, phase) in enumerate(candidates):
        hit = np.isfinite(s) & (s > 0.05) & (s < best)
        if not hit.any():
            continue
        P = C[:, None] + d[:, hit] * s[hit]
        inside = np.abs(P[0]) <= WALL_X + 1e-9
        inside &= P[2] <= BACK_Z + 1e-9
        inside &= P[1] <= GROUND_Y + 1e-9
        inside &= P[1] >= -8.0  # buildings and back wall are 9.5 m tall
        idx = np.flatnonzero(hit)[inside]
        best[idx] = s[idx]
        b = P[ib, inside]
        if ib == 2:  # along z: logarithmic, so far surfaces seen at grazing angles do not alias
            b = 6.0 * np.log1p(np.maximum(b, 0.0))
        colour[idx] = _texture(P[ia, inside], b, phase)
        surface[idx] = label
    depth = np.where(np.isfinite(best), best, 0.0).reshape(h, w)
    rgb = colour.reshape(h, w, 3)
    surface = surface.reshape(h, w)
    if patch:
        r0, c0, size = h // 3, w // 3, max(3, h // 4)
        yy, xx = np.mgrid[0:size, 0:size]
        rgb = rgb.copy()
        rgb[r0 : r0 + size, c0 : c0 + size] = 0.3 + 0.4 * ((xx + yy) % 3)[:, :, None] / 2
        depth = depth.copy()
        depth[r0 : r0 + size, c0 : c0 + size] = 5.0
        surface = surface.copy()
        surface[r0 : r0 + size, c0 : c0 + size] = 4
    if labels:
        return rgb, depth, surface
    return rgb, depth


def pose(z: float, yaw: float = 0.0, x: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at forward position ``z`` turned by ``yaw`` (radians, about y)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, 0.0, z]
    return T


@dataclass
class Frame:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, metres, 0 = sky
    K: np.ndarray
    T_world_cam: np.ndarray
    frame_index: int


def video(
    n: int,
    h: int,
    w: int,
    *,
    speed: float = 0.8,
    yaw_rate: float = 0.0,
    start: float = 0.0,
    patch: bool = False,
) -> list[Frame]:
    """``n`` frames of the street at ``speed`` metres and ``yaw_rate`` radians per frame."""
    K = intrinsics(h, w)
    out = []
    for i in range(n):
        T = pose(start + speed * i, yaw_rate * i, x=0.3 * np.sin(0.2 * i))
        rgb, depth = render(K, T, h, w, patch=patch)
        out.append(
            Frame(
                np.clip(rgb * 255 + 0.5, 0, 255).astype(np.uint8), depth.astype(np.float32), K, T, i
            )
        )
    return out


def write_video_dataset(
    root: Path,
    sequences: dict[str, list[Frame]],
    splits: dict[str, str],
    *,
    frame_index: bool = True,
    poses: bool = True,
    gt: bool = True,
    sparse_rows: int = 3,
    frame_names=None,
) -> Path:
    """Write a sparsetools dataset (PNG files + manifest.parquet) of the given sequences.

    Sparse depth: every ``sparse_rows``-th row of the ground truth (a cheap "LiDAR").
    ``frame_names`` maps (sequence, position) to the frame name (default ``%06d``).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from sparsetools.io.dataset import (
        MANIFEST_SCHEMA,
        METADATA_INFO_KEY,
        METADATA_VERSION_KEY,
        REFERENCE_COLUMNS,
        SCHEMA_VERSION,
        file_sha256,
    )
    from sparsetools.io.image import write_depth_png, write_image

    rows = []
    for seq, frames in sequences.items():
        for k, fr in enumerate(frames):
            name = frame_names(seq, k) if frame_names else f"{k:06d}"
            sid = f"{seq}/{name}"
            h, w = fr.depth.shape
            sparse = np.zeros_like(fr.depth)
            sparse[::sparse_rows] = fr.depth[::sparse_rows]
            sparse[sparse > 80] = 0
            paths = {"rgb": f"rgb/{sid}.png", "sparse": f"sparse/{sid}.png", "gt": f"gt/{sid}.png"}
            for p in paths.values():
                (root / p).parent.mkdir(parents=True, exist_ok=True)
            write_image(root / paths["rgb"], fr.rgb)
            write_depth_png(root / paths["sparse"], sparse)
            if gt:
                write_depth_png(root / paths["gt"], fr.depth)
            row = {
                "id": sid,
                "sequence": seq,
                "frame": name,
                "split": splits[seq],
                "width": w,
                "height": h,
                "fx": float(fr.K[0, 0]),
                "fy": float(fr.K[1, 1]),
                "cx": float(fr.K[0, 2]),
                "cy": float(fr.K[1, 2]),
                "rgb_path": paths["rgb"],
                "sparse_path": paths["sparse"],
                "gt_path": paths["gt"] if gt else None,
                "n_sparse": int((sparse > 0).sum()),
                "density": float((sparse > 0).mean()),
                "n_gt": int((fr.depth > 0).sum()) if gt else None,
                "source": "synthetic",
                "rgb_sha256": file_sha256(root / paths["rgb"]),
                "sparse_sha256": file_sha256(root / paths["sparse"]),
                "gt_sha256": file_sha256(root / paths["gt"]) if gt else None,
            }
            if frame_index:
                row["frame_index"] = fr.frame_index
            if poses:
                row["T_world_cam"] = [float(v) for v in fr.T_world_cam.ravel()]
            rows.append(row)
    # a schema-2 manifest: the columns of --store reference are written only when used
    fields = [f for f in MANIFEST_SCHEMA if f.name not in REFERENCE_COLUMNS]
    if frame_index and "frame_index" not in MANIFEST_SCHEMA.names:
        fields.append(pa.field("frame_index", pa.int32()))
    if poses and "T_world_cam" not in MANIFEST_SCHEMA.names:
        fields.append(pa.field("T_world_cam", pa.list_(pa.float64())))
    schema = pa.schema(fields)
    columns = {f.name: pa.array([r.get(f.name) for r in rows], type=f.type) for f in schema}
    meta = {
        METADATA_VERSION_KEY: str(SCHEMA_VERSION).encode(),
        METADATA_INFO_KEY: json.dumps({}).encode(),
    }
    table = pa.table(columns, schema=schema).replace_schema_metadata(meta)
    root.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, root / "manifest.parquet")
    return root


# -- tests of the helpers themselves (the other tests rely on them) --------------------------------
def test_render_ground_depth_is_the_plane():
    h, w = 24, 32
    K = intrinsics(h, w)
    _, depth = render(K, np.eye(4), h, w)
    # bottom row centre: a ray with y > 0 hits the ground at depth 1.5 / ((v - cy) / fy)
    v = h - 1
    expected = GROUND_Y / ((v - K[1, 2]) / K[1, 1])
    assert depth[v, w // 2] == pytest.approx(expected, rel=1e-9)
    # straight ahead the top row passes over the 9.5 m back wall: sky
    assert depth[0, w // 2] == 0
    # a pixel on the right wall at depth s has x = 6 m
    u = w - 1
    row = np.flatnonzero(depth[:, u] > 0)[0]
    assert (u - K[0, 2]) / K[0, 0] * depth[row, u] == pytest.approx(WALL_X, rel=1e-9)


def test_video_poses_and_dataset(tmp_path):
    from sparsetools.io.dataset_reader import DatasetReader

    frames = video(4, 16, 24)
    assert frames[0].T_world_cam[2, 3] == 0 and frames[3].T_world_cam[2, 3] == pytest.approx(2.4)
    ds = write_video_dataset(tmp_path / "ds", {"a": frames}, {"a": "train"})
    reader = DatasetReader(ds)
    assert len(reader) == 4 and "frame_index" in reader.manifest.column_names
    s = reader.sample(1)
    np.testing.assert_array_equal(s["rgb"], frames[1].rgb)
    np.testing.assert_allclose(s["gt"], frames[1].depth, atol=1 / 256)
