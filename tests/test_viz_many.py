"""``viz`` over many frames: contact sheets (``--sheet``), videos (``--video``), folder,
sequence-tree and dataset inputs, ``--frame-range``; the pure pieces in ``ops.viz``."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.io.image import read_depth_png, read_image, write_depth_png, write_image
from sparsetools.ops.colormap import overlay_depth
from sparsetools.ops.viz import contact_sheet, fit_picture, label_panel
from sparsetools.validate import parse_frame_range

ROOT = Path(__file__).resolve().parent.parent
SYNTH = ROOT / "sample_data" / "synthetic"
W, H = 96, 48
MARGIN = 2  # pipeline.viz.SHEET_MARGIN


def run(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and ".sparsetools" not in p.parts:
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def make_tree(root: Path, keys, *, seed=0, width=W, height=H, with_images=True, smooth=False):
    """Depth maps ``root/depth/<key>.png`` and images ``root/image/<key>.png`` (noise, or with
    ``smooth`` a gradient of another colour per frame, which a video codec keeps); returns the
    maps and images by key."""
    rng = np.random.default_rng(seed)
    maps, imgs = {}, {}
    for key in keys:
        d = np.where(rng.random((height, width)) < 0.1, rng.uniform(1, 79, (height, width)), 0)
        write_depth_png(root / "depth" / f"{key}.png", d)
        maps[key] = read_depth_png(root / "depth" / f"{key}.png")
        if with_images:
            img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
            if smooth:
                ramp = np.linspace(0, 120, width)[None, :, None] + rng.uniform(0, 130, 3)
                img = np.broadcast_to(ramp, (height, width, 3)).astype(np.uint8)
            write_image(root / "image" / f"{key}.png", img)
            imgs[key] = img
    return maps, imgs


# -- pure pieces ------------------------------------------------------------------------------------
def test_parse_frame_range():
    assert parse_frame_range("") == (None, None, 1)
    assert parse_frame_range("2:5") == (2, 5, 1)
    assert parse_frame_range("::10") == (None, None, 10)
    assert parse_frame_range("-3:") == (-3, None, 1)
    assert parse_frame_range("1:9:2") == (1, 9, 2)
    for bad in ("5", "a:b", "1:2:0", "1:2:-1", "1:2:3:4"):
        with pytest.raises(ParameterError, match="frame_range|frame-range"):
            parse_frame_range(bad)


def test_fit_picture_keeps_aspect_and_centres():
    img = np.full((10, 40, 3), 7, np.uint8)
    out = fit_picture(img, (20, 20), background=255)
    assert out.shape == (20, 20, 3)
    rows = np.nonzero(np.any(out != 255, axis=(1, 2)))[0]
    # 40x10 scaled by 0.5 -> 20x5, centred vertically: rows 7..11
    assert rows.min() == 7 and rows.max() == 11
    assert np.all(out[7:12] == 7) and np.all(out[:7] == 255) and np.all(out[12:] == 255)
    same = fit_picture(img, (40, 10))
    assert np.array_equal(same, img) and same is not img


def test_contact_sheet_layout_blank_cells_and_one_label_per_tile():
    rng = np.random.default_rng(0)
    tiles = [rng.integers(0, 200, (30, 60, 3), dtype=np.uint8) for _ in range(3)]
    page = contact_sheet(tiles, ["a", "b", "c"], grid=(2, 2), margin=2)
    th, tw = 30 + 4, 60 + 4
    assert page.shape == (2 * th, 2 * tw, 3)
    # each tile sits at its cell's margin, row by row; the top rows hold no label
    for i, tile in enumerate(tiles):
        r, c = divmod(i, 2)
        cell = page[r * th + 2 : r * th + 2 + 30, c * tw + 2 : c * tw + 2 + 60]
        np.testing.assert_array_equal(cell[:12], tile[:12])
        assert np.array_equal(cell, label_panel(tile, "abc"[i], corner="bottom-left"))
    assert np.all(page[th:, tw:] == 255)  # the fourth cell is blank
    assert np.all(page[:2] == 255) and np.all(page[:, :2] == 255)  # margins
    # a label is drawn once: the changed pixels form one line of text, at most as tall as
    # one glyph with its outline (two offset copies would be taller or doubled)
    plain = contact_sheet(tiles, None, grid=(2, 2), margin=2)
    changed = np.any(page != plain, axis=2)[:th, :tw]
    ys = np.nonzero(changed)[0]
    (_, text_h), base = cv2.getTextSize("a", cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)
    assert ys.min() > th // 2 and ys.max() - ys.min() <= text_h + base + 4
    with pytest.raises(ParameterError, match="tiles of a 2x2 grid: must be <= 4"):
        contact_sheet(tiles * 2, grid=(2, 2))
    with pytest.raises(ParameterError, match="label"):
        contact_sheet(tiles, ["a"], grid=(2, 2))
    # a fixed cell size: tiles are fitted (aspect kept), the page is grid x cell
    page = contact_sheet(tiles, grid=(3, 1), tile_size=(40, 50), margin=0)
    assert page.shape == (50, 120, 3)


def test_label_bottom_left_corner():
    img = np.full((60, 200, 3), 100, np.uint8)
    out = label_panel(img, "0000000005", corner="bottom-left")
    ys, xs = np.nonzero(np.any(out != img, axis=2))
    assert ys.min() > 30 and xs.min() < 20
    with pytest.raises(ParameterError):
        label_panel(img, "x", corner="middle")


# -- sheets ----------------------------------------------------------------------------------------
def test_sheet_pages_tiles_and_size(tmp_path):
    keys = [f"{i:06d}" for i in range(7)]
    maps, imgs = make_tree(tmp_path, keys)
    out = tmp_path / "sheets"
    args = ["viz", tmp_path / "depth", "--image", tmp_path / "image", "--sheet",
            "--grid", "2x2", "--tile-width", "64", "--dilate", "0", "--no-colorbar", "-o", out]  # fmt: skip
    res = run(args)
    assert res.exit_code == 0, res.output
    pages = sorted(p.name for p in out.glob("*.png"))
    assert pages == ["sheet_0001.png", "sheet_0002.png"]  # ceil(7 / 4)
    tw = 64
    th = round(H * (tw - 2 * MARGIN) / W) + 2 * MARGIN  # the frames' aspect at the tile width
    for name in pages:
        assert read_image(out / name).shape == (2 * th, 2 * tw, 3)
    page2 = read_image(out / "sheet_0002.png")
    cells = [page2[r * th : (r + 1) * th, c * tw : (c + 1) * tw] for r in (0, 1) for c in (0, 1)]
    assert all(np.any(c != 255) for c in cells[:3]) and np.all(cells[3] == 255)
    # the first tile of page 1 is frame 000000's overlay, shrunk to the cell (label at the
    # bottom: compare the top rows)
    page1 = read_image(out / "sheet_0001.png")
    inner = page1[MARGIN : th - MARGIN, MARGIN : tw - MARGIN]
    expect = cv2.resize(
        overlay_depth(imgs[keys[0]], maps[keys[0]], dilate=0),
        (tw - 2 * MARGIN, th - 2 * MARGIN),
        interpolation=cv2.INTER_AREA,
    )
    np.testing.assert_array_equal(inner[:10], expect[:10])
    # tile 5 (page 2, first cell) is frame 000004: tiles follow the sorted keys
    expect4 = cv2.resize(overlay_depth(imgs[keys[4]], maps[keys[4]], dilate=0),
                         (tw - 2 * MARGIN, th - 2 * MARGIN), interpolation=cv2.INTER_AREA)  # fmt: skip
    np.testing.assert_array_equal(page2[MARGIN : MARGIN + 10, MARGIN : tw - MARGIN], expect4[:10])

    # rerun with the same inputs and settings: nothing is drawn again
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.png")}
    res = run([*args, "--json"])
    assert res.exit_code == 0
    summary = json.loads(res.stdout)
    assert summary["processed"] == 0 and summary["skipped_existing"] == 2
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.png")} == before
    # other settings are refused, and allowed with --overwrite (the stale page goes)
    changed = [a if a != "2x2" else "4x2" for a in args]
    res = run(changed)
    assert res.exit_code == 1 and "--grid" in res.output and "--overwrite" in res.output
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.png")} == before
    res = run([*changed, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.glob("*.png")) == ["sheet_0001.png"]
    assert read_image(out / "sheet_0001.png").shape == (2 * th, 4 * tw, 3)


def test_sheet_with_colorbar_two_inputs_and_frame_range(tmp_path):
    keys = [f"{i:04d}" for i in range(6)]
    make_tree(tmp_path / "a", keys, seed=1)
    make_tree(tmp_path / "b", keys, seed=2, with_images=False)
    out = tmp_path / "s"
    res = run(["viz", tmp_path / "a" / "depth", tmp_path / "b" / "depth", "--image",
               tmp_path / "a" / "image", "--sheet", "--grid", "2x1", "--tile-width", "100",
               "--frame-range", "1::2", "-o", out, "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["frames"] == 3 and summary["pages"] == 2  # frames 1, 3, 5
    page = read_image(out / "sheet_0001.png")
    inner = 100 - 2 * MARGIN
    # two panels stacked in a tile, 4 px apart, then the colour bar below the grid
    tile_h = 2 * round(H * inner / W) + 4 + 2 * MARGIN
    assert page.shape[1] == 200 and page.shape[0] > tile_h
    assert np.all(page[tile_h : tile_h + 4] == 255)  # the gap above the colour bar
    assert not np.all(page[tile_h + 4 :] == 255)


def test_sheet_of_the_sample_data(tmp_path):
    out = tmp_path / "s"
    res = run(["viz", SYNTH / "depth_gt", "--image", SYNTH / "image_2", "--sheet", "--grid",
               "2x1", "-o", out])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.glob("*.png")) == ["sheet_0001.png", "sheet_0002.png"]
    page = read_image(out / "sheet_0002.png")
    assert page.shape[1] == 2 * 320
    tile_h = round(375 * (320 - 2 * MARGIN) / 1242) + 2 * MARGIN
    assert np.all(page[:tile_h, 320:] == 255)  # one frame on the last page


def test_sequence_tree_tiles_follow_the_keys(tmp_path):
    keys = ["drive_b/0000", "drive_a/0001", "drive_a/0000"]
    maps, imgs = make_tree(tmp_path, keys)
    out = tmp_path / "s"
    res = run(["viz", tmp_path / "depth", "--image", tmp_path / "image", "--sheet", "--grid",
               "3x1", "--tile-width", "100", "--dilate", "0", "--json", "-o", out])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["frames"] == 3
    page = read_image(out / "sheet_0001.png")
    inner = (100 - 2 * MARGIN, round(H * (100 - 2 * MARGIN) / W))
    for i, key in enumerate(sorted(keys)):  # (sequence, frame) order, across sequences
        expect = cv2.resize(overlay_depth(imgs[key], maps[key], dilate=0), inner,
                            interpolation=cv2.INTER_AREA)  # fmt: skip
        cell = page[MARGIN : MARGIN + 10, i * 100 + MARGIN : (i + 1) * 100 - MARGIN]
        np.testing.assert_array_equal(cell, expect[:10])


# -- videos ----------------------------------------------------------------------------------------
def read_video(path: Path):
    cap = cv2.VideoCapture(str(path))
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f[:, :, ::-1])
    cap.release()
    return count, size, frames


def test_video_frame_count_size_and_content(tmp_path):
    keys = [f"seq1/{i:04d}" for i in range(5)] + [f"seq2/{i:04d}" for i in range(3)]
    maps, imgs = make_tree(tmp_path, keys, width=95, height=47, smooth=True)  # odd: padded
    out = tmp_path / "v"
    args = ["viz", tmp_path / "depth", "--image", tmp_path / "image", "--video", "--fps", "5",
            "--no-colorbar", "-o", out]  # fmt: skip
    res = run(args)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.glob("*.mp4")) == ["seq1.mp4", "seq2.mp4"]
    for name, n in (("seq1.mp4", 5), ("seq2.mp4", 3)):
        count, size, frames = read_video(out / name)
        assert count == n and len(frames) == n
        assert size == (96, 48) and frames[0].shape == (48, 96, 3)
    # lossy, but close to the overlay at a coarser scale (4x4 block means; rows away from
    # the frame key in the bottom-left corner), and closer than to another frame's
    _, _, frames = read_video(out / "seq1.mp4")

    def blocks(rgb):
        return cv2.resize(rgb[:24, :92], (23, 6), interpolation=cv2.INTER_AREA).astype(float)

    got = blocks(np.ascontiguousarray(frames[2]))
    err = np.abs(got - blocks(overlay_depth(imgs["seq1/0002"], maps["seq1/0002"]))).mean()
    other = np.abs(got - blocks(overlay_depth(imgs["seq1/0000"], maps["seq1/0000"]))).mean()
    assert err < 8 and err < other / 2
    cap = cv2.VideoCapture(str(out / "seq1.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(5)
    cap.release()
    # rerun: a no-op
    before = tree_hash(out)
    res = run([*args, "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["processed"] == 0
    assert tree_hash(out) == before
    res = run([a if a != "5" else "10" for a in args])
    assert res.exit_code == 1 and "--fps" in res.output
    assert tree_hash(out) == before


def test_video_of_the_sample_data_side_by_side(tmp_path):
    out = tmp_path / "v"
    res = run(["viz", SYNTH / "depth_gt", SYNTH / "depth_gt", "--image", SYNTH / "image_2",
               "--video", "--labels", "GT,GT again", "-o", out])  # fmt: skip
    assert res.exit_code == 0, res.output
    count, size, frames = read_video(out / "video.mp4")  # a flat folder: video.mp4
    assert count == 3 and len(frames) == 3
    assert size[0] == 1242 and size[1] > 2 * 375  # two panels stacked + the colour bar


# -- one frame, errors -----------------------------------------------------------------------------
def test_folder_with_one_frame_gives_the_single_picture(tmp_path):
    make_tree(tmp_path, ["000007"])
    by_file = tmp_path / "file.png"
    by_folder = tmp_path / "folder.png"
    assert run(["viz", tmp_path / "depth" / "000007.png", "--image",
                tmp_path / "image" / "000007.png", "-o", by_file]).exit_code == 0  # fmt: skip
    res = run(["viz", tmp_path / "depth", "--image", tmp_path / "image", "-o", by_folder])
    assert res.exit_code == 0, res.output
    assert by_file.read_bytes() == by_folder.read_bytes()
    # several frames without --sheet / --video: a usage error; --frame-range picks one
    make_tree(tmp_path, ["000008"], seed=5)
    res = run(["viz", tmp_path / "depth", "-o", tmp_path / "x.png"])
    assert res.exit_code == 2 and "--sheet or --video" in res.output
    assert not (tmp_path / "x.png").exists()
    res = run(["viz", tmp_path / "depth", "--image", tmp_path / "image", "--frame-range", "0:1",
               "-o", tmp_path / "y.png"])  # fmt: skip
    assert res.exit_code == 0 and read_image(tmp_path / "y.png").shape[1] == W


@pytest.mark.parametrize(
    "case,code",
    [
        ("empty folder", 1),
        ("unmatched images", 1),
        ("unmatched second input", 1),
        ("bad grid", 2),
        ("zero grid", 2),
        ("sheet and video", 2),
        ("picture name for a folder", 2),
        ("range selects nothing", 1),
        ("bad range", 2),
        ("split without dataset", 2),
        ("fps with sheet", 2),
    ],
)
def test_bad_inputs_one_line_no_output(tmp_path, case, code):
    keys = [f"{i:04d}" for i in range(3)]
    make_tree(tmp_path, keys)
    make_tree(tmp_path / "few", keys[:1])
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out"
    depth = tmp_path / "depth"
    args = {
        "empty folder": [tmp_path / "empty", "--sheet"],
        "unmatched images": [depth, "--image", tmp_path / "few" / "image", "--sheet"],
        "unmatched second input": [depth, tmp_path / "few" / "depth", "--video"],
        "bad grid": [depth, "--sheet", "--grid", "4by3"],
        "zero grid": [depth, "--sheet", "--grid", "0x3"],
        "sheet and video": [depth, "--sheet", "--video"],
        "picture name for a folder": [depth, "--sheet"],
        "range selects nothing": [depth, "--sheet", "--frame-range", "10:20"],
        "bad range": [depth, "--sheet", "--frame-range", "1:2:0"],
        "split without dataset": [depth, "--sheet", "--split", "train"],
        "fps with sheet": [depth, "--sheet", "--fps", "3"],
    }[case]
    target = tmp_path / "out.png" if case == "picture name for a folder" else out
    res = run(["viz", *args, "-o", target])
    assert res.exit_code == code, res.output
    assert "Traceback" not in res.output
    errors = [line for line in res.output.splitlines() if line.startswith("Error")]
    assert len(errors) == 1
    assert not out.exists() and not (tmp_path / "out.png").exists()


# -- datasets --------------------------------------------------------------------------------------
@pytest.fixture
def dataset(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "in"
    for seq in ("s1", "s2", "s3", "s4"):
        for f in range(2):
            key = f"{seq}/{f:04d}"
            write_image(root / "rgb" / f"{key}.png", rng.integers(0, 256, (16, 32, 3), np.uint8))
            d = np.where(rng.random((16, 32)) < 0.2, rng.uniform(1, 60, (16, 32)), 0)
            write_depth_png(root / "sparse" / f"{key}.png", d)
            write_depth_png(root / "gt" / f"{key}.png", rng.uniform(1, 60, (16, 32)))
    (root / "calib.json").write_text(json.dumps({
        "K": [[30.0, 0, 15.5], [0, 30.0, 7.5], [0, 0, 1]], "T_cam_from_sensor": np.eye(4).tolist(),
    }))  # fmt: skip
    ds = tmp_path / "ds"
    res = run(["dataset", "build", "-o", ds, "--rgb", root / "rgb", "--sparse", root / "sparse",
               "--gt", root / "gt", "--calib", root / "calib.json", "--splits", "0.5,0.5"])  # fmt: skip
    assert res.exit_code == 0, res.output
    return ds


def test_dataset_sheet_by_split(dataset, tmp_path):
    from sparsetools.io.dataset_reader import DatasetReader

    reader = DatasetReader(dataset)
    split = reader.splits[0]
    n = len(reader.split(split))
    out = tmp_path / "s"
    res = run(["viz", dataset, "--split", split, "--sheet", "--grid", "3x1", "--tile-width",
               "64", "--no-colorbar", "--json", "-o", out])  # fmt: skip
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["frames"] == n and summary["pages"] == math.ceil(n / 3)
    page = read_image(out / "sheet_0001.png")
    # sparse and GT stacked in each tile
    assert page.shape == (2 * round(16 * 60 / 32) + 4 + 2 * MARGIN, 3 * 64, 3)
    # the dataset is not written to; a rerun is a no-op
    assert not any(p.name.startswith("sheet") for p in dataset.rglob("*"))
    res = run(["viz", dataset, "--split", split, "--sheet", "--grid", "3x1", "--tile-width",
               "64", "--no-colorbar", "--json", "-o", out])  # fmt: skip
    assert json.loads(res.stdout)["processed"] == 0
    # a dataset takes no --image, is given alone, and names its splits
    res = run(["viz", dataset, "--image", tmp_path / "s", "--sheet", "-o", tmp_path / "t"])
    assert res.exit_code == 2
    res = run(["viz", dataset, "--split", "nope", "--sheet", "-o", tmp_path / "t"])
    assert res.exit_code == 1 and "no split 'nope'" in res.output
    res = run(["viz", dataset, "-o", tmp_path / "t.png"])
    assert res.exit_code == 2 and "dataset" in res.output
    assert not (tmp_path / "t").exists() and not (tmp_path / "t.png").exists()


def test_dataset_video_per_sequence(dataset, tmp_path):
    out = tmp_path / "v"
    res = run(["viz", dataset, "--video", "--no-colorbar", "-o", out])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in out.glob("*.mp4"))
    assert names == ["s1.mp4", "s2.mp4", "s3.mp4", "s4.mp4"]
    count, size, frames = read_video(out / "s1.mp4")
    assert count == 2 and len(frames) == 2 and size == (32, 2 * 16 + 4)
