"""A synthetic video folder as a dataset: frames keyed by sequence, camera poses and times kept."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from sparsetools.cli.main import cli


def run(*args):
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    assert r.exit_code == 0, r.output
    return r


def test_video_folder_gives_sequences_poses_and_times(tmp_path):
    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.io.poses import read_kitti_poses, read_times

    video = tmp_path / "video"
    run("synth-scene", "-o", video, "--video", "--sequences", "2", "--frames", "3",
        "--image-size", "96x32", "--antialias", "1")  # fmt: skip
    run("beams", video, "--n", "16", "-o", tmp_path / "b16")
    run("project", tmp_path / "b16", "--calib", video, "--image", video, "-o", tmp_path / "d16")
    r = run("dataset", "build", "-o", tmp_path / "ds", "--rgb", video, "--sparse",
            tmp_path / "d16", "--gt", video, "--json")  # fmt: skip
    s = json.loads(r.stdout)
    assert s["samples"] == 6 and s["sequences"] == 2
    rows = {r["id"]: r for r in DatasetReader(tmp_path / "ds").manifest.to_pylist()}
    for seq in ("seq_0000", "seq_0001"):
        poses = read_kitti_poses(video / seq / "poses.txt")
        times = read_times(video / seq / "times.txt")
        for i in range(3):
            row = rows[f"{seq}/{i:010d}"]
            assert row["sequence"] == seq and row["frame_index"] == i
            np.testing.assert_array_equal(np.reshape(row["T_world_cam"], (4, 4)), poses[i])
            assert row["timestamp"] == times[i]
            assert row["fx"] is not None and row["n_gt"] > 0
