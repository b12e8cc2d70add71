"""Frame triplets from a dataset's sequences: order, neighbours, intrinsics, augmentation, MCIE."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sparsetools.errors import FormatError, ParameterError
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.ops.enhance import apply_lut, mcie_lut
from sparsetools.train.data import collate
from sparsetools.train.selfsup.data import (
    TripletDataset,
    frame_poses,
    frame_triplets,
    natural_key,
    sequence_frames,
)
from test_selfsup_scene import video, write_video_dataset


@pytest.fixture(scope="module")
def frames():
    return video(5, 16, 24)


def ids(reader, triplets):
    return [
        tuple(reader.row(i)["id"] for i in (t.previous, t.target, t.following)) for t in triplets
    ]


def test_natural_order_without_frame_index(tmp_path, frames):
    # frame names whose natural order differs from their string order, and two sequences
    names = {0: "f8", 1: "f9", 2: "f10", 3: "f11", 4: "f100"}
    ds = write_video_dataset(
        tmp_path / "ds",
        {"a": frames, "b": frames[:3]},
        {"a": "train", "b": "train"},
        frame_index=False,
        frame_names=lambda seq, k: names[k],
    )
    reader = DatasetReader(ds).split("train")
    order = sequence_frames(reader)
    assert [reader.row(i)["frame"] for i in order["a"]] == ["f8", "f9", "f10", "f11", "f100"]
    got = ids(reader, frame_triplets(reader))
    assert got == [
        ("a/f8", "a/f9", "a/f10"),
        ("a/f9", "a/f10", "a/f11"),
        ("a/f10", "a/f11", "a/f100"),
        ("b/f8", "b/f9", "b/f10"),
    ]
    assert natural_key("x2") < natural_key("x10") and natural_key("0009") < natural_key("0010")


def test_frame_index_orders_and_gaps_break_triplets(tmp_path):
    # names in reverse of time: frame_index decides; index 3 missing breaks (2, 3, 4)
    shuffled = video(5, 16, 24)[::-1]
    for fr, idx in zip(shuffled, (6, 4, 2, 1, 0), strict=True):
        fr.frame_index = idx
    ds = write_video_dataset(tmp_path / "ds", {"a": shuffled}, {"a": "train"})
    reader = DatasetReader(ds).split("train")
    got = ids(reader, frame_triplets(reader))
    # time order: 0 (a/000004), 1 (a/000003), 2 (a/000002), 4 (a/000001), 6 (a/000000)
    assert got == [("a/000004", "a/000003", "a/000002")]


def test_duplicate_frame_index_is_refused(tmp_path):
    twins = [video(1, 16, 24)[0], video(1, 16, 24)[0]]
    ds = write_video_dataset(tmp_path / "ds", {"a": twins}, {"a": "train"})
    with pytest.raises(FormatError, match="two frames with frame_index 0"):
        sequence_frames(DatasetReader(ds))


def test_no_triplet_and_no_intrinsics(tmp_path, frames):
    ds = write_video_dataset(tmp_path / "short", {"a": frames[:2]}, {"a": "train"})
    with pytest.raises(ParameterError, match="3 or more consecutive frames"):
        TripletDataset(ds, "train")
    import pyarrow as pa
    import pyarrow.parquet as pq

    ds = write_video_dataset(tmp_path / "nok", {"a": frames}, {"a": "train"})
    table = pq.read_table(ds / "manifest.parquet")
    i = table.column_names.index("fx")
    table = table.set_column(i, "fx", pa.array([None] * len(table), pa.float64()))
    pq.write_table(table, ds / "manifest.parquet")
    with pytest.raises(FormatError, match="no intrinsics"):
        TripletDataset(ds, "train")


def test_items_crop_and_intrinsics(tmp_path, frames):
    ds = write_video_dataset(tmp_path / "ds", {"a": frames}, {"a": "train"})
    data = TripletDataset(ds, "train", crop=(12, 20))
    assert len(data) == 3 and data.output_sizes() == {(12, 20)}
    item = data[0]
    assert item["frames"].shape == item["inputs"].shape == (3, 3, 12, 20)
    # bottom-centre crop: rows 4..15, columns 2..21
    np.testing.assert_array_equal(
        (item["frames"][1].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8),
        frames[1].rgb[4:, 2:22],
    )
    np.testing.assert_array_equal(item["frames"][0].numpy(), item["inputs"][0].numpy())  # no jitter
    K = frames[1].K
    np.testing.assert_allclose(
        item["K"].numpy(),
        [[K[0, 0], 0, K[0, 2] - 2], [0, K[1, 1], K[1, 2] - 4], [0, 0, 1]],
        rtol=1e-6,
    )
    assert data.sample_id(0) == "a/000001"
    batch = collate([data[0], data[1]])
    assert batch["frames"].shape == (2, 3, 3, 12, 20) and batch["index"].tolist() == [0, 1]


def test_flip_follows_the_intrinsics_and_jitter_only_the_inputs(tmp_path, frames):
    ds = write_video_dataset(tmp_path / "ds", {"a": frames}, {"a": "train"})
    plain = TripletDataset(ds, "train")
    aug = TripletDataset(ds, "train", augment=True, seed=3, jitter=0.3)
    w = frames[0].rgb.shape[1]
    flips = 0
    for epoch in range(6):
        aug.set_epoch(epoch)
        for i in range(len(aug)):
            a, p = aug[i], plain[i]
            flipped = not torch.equal(a["frames"], p["frames"])
            if flipped:
                flips += 1
                torch.testing.assert_close(a["frames"], p["frames"].flip(-1))
                torch.testing.assert_close(a["sparse"], p["sparse"].flip(-1))
                assert float(a["K"][0, 2]) == pytest.approx(w - 1 - float(p["K"][0, 2]))
            else:
                torch.testing.assert_close(a["K"], p["K"])
            # jitter changes the network inputs only, with one set of factors per triplet
            assert not torch.equal(a["inputs"], a["frames"])
            again = aug[i]
            torch.testing.assert_close(
                again["inputs"], a["inputs"]
            )  # seeded by (seed, epoch, index)
    assert 0 < flips < 6 * len(aug)


def test_mcie_one_table_per_triplet_from_the_target(tmp_path):
    dark = [video(1, 16, 24)[0] for _ in range(3)]
    for k, fr in enumerate(dark):
        fr.rgb = (fr.rgb // (4 + k)).astype(np.uint8)  # dark frames of differing brightness
        fr.frame_index = k
    ds = write_video_dataset(tmp_path / "ds", {"a": dark}, {"a": "train"})
    item = TripletDataset(ds, "train", mcie=True, mcie_clip=0.01)[0]
    lut = mcie_lut(dark[1].rgb, clip=0.01)
    for k in range(3):
        expected = apply_lut(dark[k].rgb, lut).astype(np.float32) / 255
        np.testing.assert_array_equal(item["frames"][k].numpy().transpose(1, 2, 0), expected)
        np.testing.assert_array_equal(
            item["inputs"][k].numpy().transpose(1, 2, 0), dark[k].rgb / np.float32(255)
        )
    # the table is shared: the darker source frame stays darker than the target after it
    assert item["frames"][2].mean() < item["frames"][1].mean()


def test_poses(tmp_path, frames):
    ds = write_video_dataset(tmp_path / "ds", {"a": frames}, {"a": "train"})
    poses = frame_poses(DatasetReader(ds))
    np.testing.assert_array_equal(poses[2], frames[2].T_world_cam)
    ds2 = write_video_dataset(tmp_path / "np", {"a": frames}, {"a": "train"}, poses=False)
    assert frame_poses(DatasetReader(ds2)) == [None] * 5
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(ds / "manifest.parquet")
    bad = [list(range(16))] * len(table)
    i = table.column_names.index("T_world_cam")
    pq.write_table(
        table.set_column(i, "T_world_cam", pa.array(bad, pa.list_(pa.float64()))),
        ds / "manifest.parquet",
    )
    with pytest.raises(FormatError, match="last row"):
        frame_poses(DatasetReader(ds))
