"""The table of (command, bad input) cases run by ``test_corpus.py``.

Each builder gets a fresh ``tmp`` folder, writes its inputs under ``tmp/in`` (hashed before
and after the run: inputs must not change) and returns the command line. The output is
``tmp/out`` unless the case says otherwise. ``expect``:

- ``"error"``: exit code 1, exactly one ``Error: ...`` line on stderr (log warnings aside)
  containing ``match``, no new output file, no temporary file;
- ``"usage"``: click's usage error, exit code 2 (only for option/argument validation);
- ``"ok"``: the documented non-error behaviour (exit 0), checked by the case's ``check``.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
from corpus_builder import (
    Case,
    H,
    Setup,
    W,
    bomb_png,
    cloud,
    corrupt_jpeg,
    corrupt_png,
    depth_map,
    depth_png_bytes,
    good_frame,
    jpeg_bytes,
    json_calib,
    kitti_calib_text,
    npy_bytes,
    npy_huge_header,
    png_bytes,
    radar_pcd_bytes,
    rgb_image,
    truncated,
    underwater_tree,
    write,
)

CASES: list[Case] = []

#: A folder no process can create anything in, root included (sysfs refuses mkdir).
UNCREATABLE = Path("/sys/kernel/sparsetools-robustness/out")
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


def case(id: str, expect: str = "error", match: str = "", **kw):
    def deco(fn):
        CASES.append(Case(id, fn, expect, match, **kw))
        return fn

    return deco


def IN(tmp: Path) -> Path:
    return tmp / "in"


def OUT(tmp: Path) -> Path:
    return tmp / "out"


def read_only_dir(tmp: Path) -> Path:
    ro = tmp / "readonly"
    ro.mkdir()
    ro.chmod(0o555)
    return ro


# ======================================================================================
# Bad clouds (shared by project and beams)
# ======================================================================================

BAD_CLOUDS = {
    # name: (file name, bytes, expected error substring)
    "truncated-bin": ("000000.bin", cloud().tobytes()[: 16 * 100 + 7], "not a multiple of 16"),
    "bin-size-multiple-of-4-not-16": ("000000.bin", cloud().tobytes()[: 16 * 100 + 4], "16"),
    "nuscenes-pcd-bin-not-multiple-of-20": ("000000.pcd.bin", b"\x00" * 44, "multiple of 20"),
    "pcd-random-bytes": ("000000.pcd", bytes(range(256)) * 8, "000000.pcd"),
    "pcd-empty": ("000000.pcd", b"", "empty"),
    "radar-pcd-truncated": ("000000.pcd", radar_pcd_bytes(20, declared=100), "truncated"),
    "radar-pcd-negative-count": ("000000.pcd", radar_pcd_bytes(0, declared=-5), "000000.pcd"),
    "ply-garbage": ("000000.ply", b"ply\nformat nonsense\n" + b"\xff" * 100, "000000.ply"),
    # Open3D 0.19 crashed the process (segmentation fault) on this cut header:
    "ply-header-cut-short": ("000000.ply", b"ply\nformat binary_little_endian 1.0\ncomment", "PLY"),
    # ... and made a cloud of ~1.8e9 uninitialised points from this one (then aborted):
    "pcd-header-without-points": (
        "000000.pcd",
        b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nDATA binary\n",
        "WIDTH",
    ),
    "pcd-header-declares-more-points": (
        "000000.pcd",
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1000000000\n"
        b"HEIGHT 1\nPOINTS 1000000000\nDATA binary\n" + b"\x00" * 120,
        "truncated",
    ),
    # Open3D corrupts its heap on repeated fields, PCL's "_" padding included (malloc abort):
    "pcd-repeated-field": (
        "000000.pcd",
        b"VERSION 0.7\nFIELDS x y z _ intensity _\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\n"
        b"COUNT 1 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n" + b"\x00" * 48,
        "repeats a field name",
    ),
    "ply-header-declares-more-vertices": (
        "000000.ply",
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + b"\x00" * 120,
        "truncated",
    ),
    "npy-garbage": ("000000.npy", b"\x93NUMPY garbage" * 10, "not a valid .npy"),
    "npy-wrong-shape": ("000000.npy", npy_bytes(np.zeros((10, 2), np.float32)), "N, C>=3"),
    "npy-pickled-objects": ("000000.npy", npy_bytes(np.array([{}, 1], dtype=object)), ".npy"),
    "npy-strings": ("000000.npy", npy_bytes(np.array([["a", "b", "c"]])), "numeric"),
    "npy-header-declares-huge-shape": ("000000.npy", npy_huge_header(), "truncated or corrupt"),
}


def _cloud_case(command: str, name: str, fname: str, data: bytes, match: str):
    @case(f"{command}/{name}", match=match)
    def build(tmp: Path) -> Setup:
        f = good_frame(IN(tmp))
        bad = write(IN(tmp) / "bad" / fname, data)
        if command == "project":
            args = ["project", bad, "--calib", f["calib"], "--image-size", f"{W}x{H}"]
        else:
            args = ["beams", bad, "--n", "4"]
        return Setup([*args, "-o", OUT(tmp)])


for _name, (_fname, _data, _match) in BAD_CLOUDS.items():
    _cloud_case("project", _name, _fname, _data, _match)
    _cloud_case("beams", _name, _fname, _data, _match)


# ======================================================================================
# project
# ======================================================================================


def _project(tmp: Path, *extra, cloud_path=None, calib=None) -> list:
    f = good_frame(IN(tmp))
    return [
        "project",
        cloud_path or f["cloud"],
        "--calib",
        calib or f["calib"],
        *(extra or ("--image-size", f"{W}x{H}")),
        "-o",
        OUT(tmp),
    ]


def _check_empty_map(tmp: Path, result) -> None:
    from sparsetools.io.image import read_depth_png

    depth = read_depth_png(OUT(tmp) / "000000.png")
    assert depth.shape == (H, W) and not depth.any()
    assert "empty depth map" in result.stderr


@case("project/zero-length-bin-is-an-empty-cloud", expect="ok")
def _(tmp):
    bad = write(IN(tmp) / "c" / "000000.bin", b"")
    return Setup(_project(tmp, cloud_path=bad), check=_check_empty_map)


@case("project/all-rows-nan-is-an-empty-cloud", expect="ok")
def _(tmp):
    pts = np.full((50, 4), np.nan, np.float32)
    bad = write(IN(tmp) / "c" / "000000.bin", pts.tobytes())

    def check(tmp, result):
        _check_empty_map(tmp, result)
        assert "dropped 50 point(s) with NaN/Inf" in result.stderr

    return Setup(_project(tmp, cloud_path=bad), check=check)


@case("project/nan-inf-rows-dropped-with-warning", expect="ok")
def _(tmp):
    pts = cloud(200)
    pts[3, 0] = np.nan
    pts[7, 2] = np.inf
    pts[9, 3] = -np.inf
    bad = write(IN(tmp) / "c" / "000000.bin", pts.tobytes())

    def check(tmp, result):
        from sparsetools.io.image import read_depth_png

        assert "dropped 3 point(s) with NaN/Inf" in result.stderr
        depth = read_depth_png(OUT(tmp) / "000000.png")
        assert np.isfinite(depth).all() and 150 <= np.count_nonzero(depth) <= 197

    return Setup(_project(tmp, cloud_path=bad), check=check)


@case("project/cloud-unknown-suffix", match="is not a .bin/.pcd/.ply/.npy file")
def _(tmp):
    bad = write(IN(tmp) / "c" / "000000.xyz", b"1 2 3\n")
    return Setup(_project(tmp, cloud_path=bad))


@case("project/folder-without-clouds", match="no *.bin/*.pcd/*.ply/*.npy files in")
def _(tmp):
    write(IN(tmp) / "c" / "readme.txt", "nothing here")
    return Setup(_project(tmp, cloud_path=IN(tmp) / "c"))


@case("project/cloud-dangling-symlink-in-folder", match="no *.bin/*.pcd/*.ply/*.npy files in")
def _(tmp):
    (IN(tmp) / "c").mkdir(parents=True)
    (IN(tmp) / "c" / "000000.bin").symlink_to(tmp / "nowhere.bin")
    return Setup(_project(tmp, cloud_path=IN(tmp) / "c"))


CALIB_TEXTS = {
    "calib-missing-key": (kitti_calib_text(drop="Tr_velo_to_cam"), "missing key 'Tr_velo_to_cam'"),
    "calib-missing-P2": (kitti_calib_text(drop="P2"), "missing key 'P2'"),
    "calib-non-numeric": (
        kitti_calib_text().replace("P2: ", "P2: abc ", 1),
        "'P2' holds non-numeric values",
    ),
    "calib-nan-value": (kitti_calib_text().replace("R0_rect: ", "R0_rect: nan ", 1), "R0_rect"),
    "calib-wrong-count": (
        kitti_calib_text().replace("Tr_velo_to_cam: ", "Tr_velo_to_cam: 1 ", 1),
        "has 13 values, expected 12",
    ),
    "calib-singular-projection": (kitti_calib_text(P2=np.zeros((3, 4))), "singular"),
    "calib-empty-file": ("", "missing key"),
    "calib-binary": (None, "not a text calibration file"),
}


def _calib_case(name, text, match):
    @case(f"project/{name}", match=match)
    def build(tmp):
        if text is None:
            c = write(IN(tmp) / "cal" / "000000.txt", b"P2: \xff\xfe\x00\x81")
        else:
            c = write(IN(tmp) / "cal" / "000000.txt", text)
        return Setup(_project(tmp, calib=c))


for _name, (_text, _match) in CALIB_TEXTS.items():
    _calib_case(_name, _text, _match)


JSON_CALIBS = {
    "json-calib-garbage": (b"{not json", "not valid JSON"),
    "json-calib-not-object": (b"[1, 2, 3]", "expected a JSON object"),
    "json-calib-missing-K": (json.dumps({"T_cam_from_sensor": np.eye(4).tolist()}), "'K'"),
    "json-calib-non-numeric-K": (
        json.dumps(json_calib(K=[["a", 0, 1], [0, 1, 1], [0, 0, 1]])),
        "non-numeric",
    ),
    "json-calib-K-wrong-shape": (json.dumps(json_calib(K=[[1, 0], [0, 1]])), "must be 3x3"),
    "json-calib-nan-K": (
        json.dumps(json_calib(K=[[float("nan"), 0, 1], [0, 1, 1], [0, 0, 1]])),
        "non-finite",
    ),
    "json-calib-bad-width": (json.dumps(json_calib(width="wide")), "width"),
    "json-calib-utf16": (json.dumps(json_calib()).encode("utf-16"), "not a text calibration file"),
}


def _json_calib_case(name, data, match):
    @case(f"project/{name}", match=match)
    def build(tmp):
        c = write(IN(tmp) / "cal" / "000000.json", data)
        return Setup(_project(tmp, calib=c))


for _name, (_data, _match) in JSON_CALIBS.items():
    _json_calib_case(_name, _data, _match)


@case("project/calib-folder-missing-this-frame", match="no such calibration file")
def _(tmp):
    good_frame(IN(tmp))
    write(IN(tmp) / "cal" / "999999.txt", kitti_calib_text())
    return Setup(_project(tmp, calib=IN(tmp) / "cal"))


@case("project/calib-folder-without-calibrations", match="--calib: no *.txt/*.json files in")
def _(tmp):
    write(IN(tmp) / "cal" / "notes.md", "x")
    return Setup(_project(tmp, calib=IN(tmp) / "cal"))


@case("project/image-for-size-corrupt", match="not a PNG or JPEG")
def _(tmp):
    img = write(IN(tmp) / "img" / "000000.png", b"\x00" * 100)
    return Setup(_project(tmp, "--image", img))


@case("project/image-for-size-decompression-bomb", match="above the limit")
def _(tmp):
    img = write(IN(tmp) / "img" / "000000.png", bomb_png())
    return Setup(_project(tmp, "--image", img))


@case("project/image-size-option-huge", match="above the limit")
def _(tmp):
    return Setup(_project(tmp, "--image-size", "200000x200000"))


@case("project/image-size-option-malformed", expect="usage", match="expected WxH")
def _(tmp):
    return Setup(_project(tmp, "--image-size", "64by32"))


@case("project/crop-outside-image", match="crop")
def _(tmp):
    return Setup(_project(tmp, "--image-size", f"{W}x{H}", "--crop", "10,10,500,500"))


@case("project/crop-malformed", expect="usage", match="WxH+LEFT+TOP")
def _(tmp):
    return Setup(_project(tmp, "--image-size", f"{W}x{H}", "--crop", "1,2"))


@case("project/negative-min-depth", expect="usage", match="must be a finite number >= 0")
def _(tmp):
    return Setup(_project(tmp, "--image-size", f"{W}x{H}", "--min-depth", "-1"))


@case("project/no-image-size", match="image size missing")
def _(tmp):
    return Setup(_project(tmp, "--format", "png"))


@case("project/kitti-object-folder-incomplete", match="no calib/")
def _(tmp):
    write(IN(tmp) / "obj" / "training" / "velodyne" / "000000.bin", cloud().tobytes())
    return Setup(["project", "--kitti-object", IN(tmp) / "obj", "-o", OUT(tmp)])


@case("project/kitti-raw-without-calibration", match="calib_cam_to_cam.txt")
def _(tmp):
    drive = IN(tmp) / "2011_09_26" / "2011_09_26_drive_0001_sync"
    write(drive / "velodyne_points" / "data" / "0000000000.bin", cloud().tobytes())
    return Setup(["project", "--kitti-raw", drive, "-o", OUT(tmp)])


@case("project/nuscenes-table-garbage", match="not valid JSON")
def _(tmp):
    root = IN(tmp) / "nus"
    for name in ("sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor"):
        write(root / "v1.0-mini" / f"{name}.json", "[]")
    write(root / "v1.0-mini" / "sample_data.json", b'[{"token": ')
    return Setup(["project", "--nuscenes", root, "-o", OUT(tmp)])


@case("project/nuscenes-record-missing-field", match="lacks 'token'")
def _(tmp):
    root = IN(tmp) / "nus"
    for name in ("sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor"):
        write(root / "v1.0-mini" / f"{name}.json", "[]")
    write(root / "v1.0-mini" / "sensor.json", json.dumps([{"channel": "RADAR_FRONT"}]))
    return Setup(["project", "--nuscenes", root, "-o", OUT(tmp)])


# -- unwritable / misplaced output (project is the reference; other commands below) ---------------


def _out_cases(command: str, build_args):
    """OUT is a file, OUT below a file, OUT inside IN (directly and via a symlink), OUT
    uncreatable, OUT read-only or in a read-only folder (run by root, these two run in a
    process that gave up the capabilities ignoring permission bits: test_corpus.py)."""

    @case(f"{command}/out-is-a-file", match="is a file, expected a folder")
    def _(tmp):
        OUT(tmp).parent.mkdir(parents=True, exist_ok=True)
        OUT(tmp).write_text("in the way")
        return Setup(build_args(tmp, OUT(tmp)))

    @case(f"{command}/out-below-a-file", match="cannot create")
    def _(tmp):
        OUT(tmp).mkdir(parents=True, exist_ok=True)
        (OUT(tmp) / "file").write_text("in the way")
        return Setup(build_args(tmp, OUT(tmp) / "file" / "sub"))

    @case(f"{command}/out-inside-in", match="inside")
    def _(tmp):
        args = build_args(tmp, None)
        return Setup(args, out=IN(tmp))

    @case(f"{command}/out-uncreatable", match="cannot create")
    def _(tmp):
        return Setup(build_args(tmp, UNCREATABLE), out=tmp / "nothing")

    @case(f"{command}/out-read-only", match="is not writable", root_only=False)
    def _(tmp):
        ro = read_only_dir(tmp)
        return Setup(build_args(tmp, ro), out=ro)

    @case(f"{command}/out-in-read-only-folder", match="cannot create", root_only=False)
    def _(tmp):
        ro = read_only_dir(tmp)
        return Setup(build_args(tmp, ro / "out"), out=ro)


def _project_out(tmp, out):
    f = good_frame(IN(tmp))
    out = out if out is not None else IN(tmp) / "velodyne" / "out"
    return ["project", IN(tmp) / "velodyne", "--calib", f["calib"], "--image-size", f"{W}x{H}",
            "-o", out]  # fmt: skip


_out_cases("project", _project_out)


@case("project/out-symlink-into-in", match="inside the input folder")
def _(tmp):
    f = good_frame(IN(tmp))
    (tmp / "link").symlink_to(IN(tmp) / "velodyne")
    args = ["project", IN(tmp) / "velodyne", "--calib", f["calib"], "--image-size", f"{W}x{H}",
            "-o", tmp / "link" / "out"]  # fmt: skip
    return Setup(args, out=IN(tmp))


@case("project/output-would-replace-input", match="would replace an input file")
def _(tmp):
    # A .npy cloud projected with --format npy into its own folder: OUT/<stem>.npy is the input.
    c = write(IN(tmp) / "c" / "000000.npy", npy_bytes(cloud(100)))
    f = good_frame(IN(tmp))
    args = ["project", c, "--calib", f["calib"], "--image-size", f"{W}x{H}", "--format", "npy",
            "--overwrite", "-o", c.parent]  # fmt: skip
    return Setup(args, out=IN(tmp))


@case("project/cloud-symlink-to-outside-is-read", expect="ok")
def _(tmp):
    # Inputs may be symbolic links anywhere (datasets are often linked in); they are only read.
    f = good_frame(tmp / "elsewhere")
    (IN(tmp) / "c").mkdir(parents=True)
    (IN(tmp) / "c" / "000000.bin").symlink_to(f["cloud"])

    def check(tmp, result):
        assert (OUT(tmp) / "000000.png").is_file()

    return Setup(_project(tmp, cloud_path=IN(tmp) / "c"), check=check, allowed_outputs=("*",))


@case("project/output-symlink-to-outside-not-followed", match="symbolic link")
def _(tmp):
    # An output path that is a symlink to a file outside OUT: refused, nothing written through
    # it, and the link (not the toolkit's) left as it is.
    victim = write(tmp / "victim" / "keep.png", b"precious")
    OUT(tmp).mkdir()
    (OUT(tmp) / "000000.png").symlink_to(victim)

    def check(tmp, result):
        assert victim.read_bytes() == b"precious"
        assert (OUT(tmp) / "000000.png").is_symlink()

    return Setup([*_project(tmp)[:-2], "--overwrite", "-o", OUT(tmp)], check=check,
                 allowed_outputs=("*",))  # fmt: skip


# ======================================================================================
# beams (bad clouds above)
# ======================================================================================


def _beams(tmp, *extra, clouds=None):
    f = good_frame(IN(tmp))
    return ["beams", clouds or f["cloud"], *extra, "-o", OUT(tmp)]


@case("beams/zero-length-bin", match="empty file")
def _(tmp):
    bad = write(IN(tmp) / "c" / "000000.bin", b"")
    return Setup(_beams(tmp, "--n", "4", clouds=bad))


@case("beams/calib-missing-key", match="missing key")
def _(tmp):
    c = write(IN(tmp) / "cal" / "x.txt", kitti_calib_text(drop="R0_rect"))
    return Setup(_beams(tmp, "--n", "4", "--calib", c, "--image-size", f"{W}x{H}"))


@case("beams/profile-json-garbage", match="cannot read the sensor profile")
def _(tmp):
    p = write(IN(tmp) / "profile.json", b'{"elevations": [1, 2,')
    return Setup(_beams(tmp, "--n", "4", "--profile", p))


@case("beams/profile-unknown-name", match="no such sensor profile")
def _(tmp):
    return Setup(_beams(tmp, "--n", "4", "--profile", "no-such-sensor"))


@case("beams/rings-out-of-range", match="--rings")
def _(tmp):
    return Setup(_beams(tmp, "--rings", "0,500"))


@case("beams/n-zero", expect="usage", match="values must be >= 1")
def _(tmp):
    return Setup(_beams(tmp, "--n", "0"))


_out_cases(
    "beams",
    lambda tmp, out: [
        "beams",
        good_frame(IN(tmp))["cloud"].parent,
        "--n",
        "4",
        "-o",
        out if out is not None else IN(tmp) / "velodyne" / "b4",
    ],
)


# ======================================================================================
# images: lowlight-synth, equalize (bad image files)
# ======================================================================================

BAD_IMAGES = {
    "image-zero-length": ("000000.png", b"", "empty"),
    "image-corrupt-png": ("000000.png", corrupt_png(), "cannot decode"),
    "image-truncated-png": ("000000.png", truncated(png_bytes(rgb_image())), "cannot decode"),
    "image-corrupt-jpeg": ("000000.jpg", corrupt_jpeg(), "cannot decode"),
    "image-decompression-bomb": ("000000.png", bomb_png(), "above the limit"),
    # Under the limit but without the data: libpng prints "Not enough image data" on fd 2.
    "image-png-shorter-than-its-header": ("000000.png", bomb_png(11000, 11000), "cannot decode"),
    "image-16-bit": ("000000.png", depth_png_bytes(depth_map()), "uint16 image"),
    "image-text-file-named-png": ("000000.png", b"hello, I am not a picture\n" * 10, "decode"),
}


def _image_case(command: str, name: str, fname: str, data: bytes, match: str):
    @case(f"{command.removesuffix('-image')}/{name}", match=match)
    def build(tmp):
        bad = write(IN(tmp) / "img" / fname, data)
        if command == "underwater":
            sea, water = underwater_tree(IN(tmp))
            (sea / "000001.png").unlink()
            write(sea / ("000001" + Path(fname).suffix), data)
            return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])
        if command == "viz-image":
            d = write(IN(tmp) / "d.png", depth_png_bytes(depth_map()))
            return Setup(["viz", d, "--image", bad, "-o", OUT(tmp) / "v.png"])
        if command == "dataset-build":
            write(IN(tmp) / "sparse" / "000000.png", depth_png_bytes(depth_map()))
            return Setup(["dataset", "build", "--rgb", bad.parent, "--sparse", IN(tmp) / "sparse",
                          "-o", OUT(tmp)])  # fmt: skip
        if command == "jbf-expand":
            r = write(IN(tmp) / "radar" / "000000.png", depth_png_bytes(depth_map(density=0.02)))
            return Setup(["jbf-expand", r, "--image", bad, "--fx", "40", "--fy", "40",
                          "-o", OUT(tmp)])  # fmt: skip
        return Setup([command, bad, "-o", OUT(tmp)])


for _command in ("lowlight-synth", "equalize", "underwater", "viz-image", "dataset-build",
                 "jbf-expand"):  # fmt: skip
    for _name, (_fname, _data, _match) in BAD_IMAGES.items():
        _image_case(_command, _name, _fname, _data, _match)


# ======================================================================================
# lowlight-synth
# ======================================================================================


def _lowlight(tmp, *extra):
    f = good_frame(IN(tmp))
    return ["lowlight-synth", f["image"], *extra, "-o", OUT(tmp)]


BAD_DEPTHS = {
    "depth-8-bit": (png_bytes(np.full((H, W), 40, np.uint8)), "8-bit files cannot hold"),
    "depth-rgb": (png_bytes(rgb_image()), "single-channel"),
    "depth-corrupt": (corrupt_png(), "cannot decode"),
    "depth-zero-length": (b"", "empty"),
    "depth-decompression-bomb": (bomb_png(), "above the limit"),
}


def _lowlight_depth_case(name, data, match):
    @case(f"lowlight-synth/{name}", match=match)
    def build(tmp):
        d = write(IN(tmp) / "dep" / "000000.png", data)
        return Setup(_lowlight(tmp, "--depth", d))


for _name, (_data, _match) in BAD_DEPTHS.items():
    _lowlight_depth_case(_name, _data, _match)


@case("lowlight-synth/depth-size-mismatch", match="depth map is 32x16")
def _(tmp):
    d = write(IN(tmp) / "dep" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    return Setup(_lowlight(tmp, "--depth", d))


@case("lowlight-synth/depth-folder-missing-frame", match="no depth map")
def _(tmp):
    write(IN(tmp) / "dep" / "999999.png", depth_png_bytes(depth_map()))
    return Setup(_lowlight(tmp, "--depth", IN(tmp) / "dep"))


@case("lowlight-synth/calib-non-numeric", match="non-numeric")
def _(tmp):
    c = write(IN(tmp) / "cal" / "000000.txt", kitti_calib_text().replace("P2: ", "P2: x ", 1))
    d = write(IN(tmp) / "dep" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(_lowlight(tmp, "--depth", d, "--calib", c))


@case("lowlight-synth/jpeg-with-extraneous-bytes-is-read-with-a-warning", expect="ok")
def _(tmp):
    # libjpeg decodes it and prints a warning on fd 2: it becomes one WARNING log line.
    good = jpeg_bytes(rgb_image())
    i = good.index(b"\xff\xdb")
    img = write(IN(tmp) / "img" / "000000.jpg", good[:i] + b"\x00" * 7 + good[i:])

    def check(tmp, result):
        assert (OUT(tmp) / "000000.png").is_file()
        warn = [ln for ln in result.stderr.splitlines() if "Corrupt JPEG data" in ln]
        assert len(warn) == 1 and warn[0].startswith("WARNING: "), result.stderr

    return Setup(["lowlight-synth", img, "-o", OUT(tmp)], check=check)


@case("lowlight-synth/not-an-image-suffix", match="not a PNG or JPEG")
def _(tmp):
    bad = write(IN(tmp) / "img" / "000000.bmp", b"BM")
    return Setup(["lowlight-synth", bad, "-o", OUT(tmp)])


@case("lowlight-synth/corrupt-record-sidecar-in-out", match="has no record of what made it")
def _(tmp):
    write(OUT(tmp) / "records" / "000000.json", b'{"config": ')
    return Setup(_lowlight(tmp))


@case("lowlight-synth/brightness-inverted", expect="usage", match="inverted")
def _(tmp):
    return Setup(_lowlight(tmp, "--brightness", "0.9,0.1"))


_out_cases(
    "lowlight-synth",
    lambda tmp, out: [
        "lowlight-synth",
        good_frame(IN(tmp))["image"].parent,
        "-o",
        out if out is not None else IN(tmp) / "image_2" / "night",
    ],
)


# ======================================================================================
# equalize
# ======================================================================================


@case("equalize/corrupt-lut-in-out", match="has no record of what made it")
def _(tmp):
    f = good_frame(IN(tmp))
    write(OUT(tmp) / "mcie_lut.json", b"\x00\x01")
    return Setup(["equalize", f["image"], "-o", OUT(tmp)])


@case("project/corrupt-run-record-in-out", match="unreadable record of what made")
def _(tmp):
    f = good_frame(IN(tmp))
    write(OUT(tmp) / ".sparsetools" / "run.json", b"{not json")
    return Setup(["project", f["cloud"], "--calib", f["calib"], "--image", f["image"], "-o",
                  OUT(tmp)])  # fmt: skip


@case("equalize/reference-not-an-input", match="neither a file nor the name of an input")
def _(tmp):
    f = good_frame(IN(tmp))
    return Setup(["equalize", f["image"], "--reference", "nope", "-o", OUT(tmp)])


@case("equalize/clip-zero", expect="usage", match="--clip': must be a finite number > 0")
def _(tmp):
    f = good_frame(IN(tmp))
    return Setup(["equalize", f["image"], "--clip", "0", "-o", OUT(tmp)])


_out_cases(
    "equalize",
    lambda tmp, out: [
        "equalize",
        good_frame(IN(tmp))["image"].parent,
        "-o",
        out if out is not None else IN(tmp) / "image_2" / "eq",
    ],
)


# ======================================================================================
# underwater
# ======================================================================================


@case("underwater/water-frame-corrupt", match="cannot decode")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    write(water / "000001.png", corrupt_png())
    return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])


@case("underwater/water-size-mismatch", match="water-only frames are")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    for p in water.iterdir():
        write(p, png_bytes(rgb_image(w=32, h=16)))
    return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])


@case("underwater/seafloor-sizes-differ", match="sequence")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    write(sea / "000002.png", png_bytes(rgb_image(w=32, h=16)))
    return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])


@case("underwater/fewer-frames-than-window", match="fewer than the median window")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    return Setup(["underwater", sea, "--water", water, "--window", "5", "-o", OUT(tmp)])


@case("underwater/water-folder-empty", match="no water-only frames")
def _(tmp):
    sea, water = underwater_tree(IN(tmp), n_water=0)
    water.mkdir(parents=True, exist_ok=True)
    return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])


@case("underwater/even-window", expect="usage", match="odd")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    return Setup(["underwater", sea, "--water", water, "--window", "4", "-o", OUT(tmp)])


@case("underwater/corrupt-settings-in-out", match="has no record of what made it")
def _(tmp):
    sea, water = underwater_tree(IN(tmp))
    write(OUT(tmp) / "underwater.json", b"{{{")
    return Setup(["underwater", sea, "--water", water, "--window", "3", "-o", OUT(tmp)])


def _underwater_out(tmp, out):
    sea, water = underwater_tree(IN(tmp))
    return ["underwater", sea, "--water", water, "--window", "3", "-o",
            out if out is not None else sea / "uw"]  # fmt: skip


_out_cases("underwater", _underwater_out)


# ======================================================================================
# viz and stats (depth files)
# ======================================================================================


def _viz_depth_case(name, data, match):
    @case(f"viz/{name}", match=match)
    def build(tmp):
        d = write(IN(tmp) / "d" / "000000.png", data)
        return Setup(["viz", d, "-o", OUT(tmp) / "v.png"])

    @case(f"stats/{name}", match=match)
    def build2(tmp):
        d = write(IN(tmp) / "d" / "000000.png", data)
        return Setup(["stats", d], out=tmp / "nothing")

    @case(f"jbf-expand/radar-{name}", match=match)
    def build3(tmp):
        f = good_frame(IN(tmp))
        r = write(IN(tmp) / "radar" / "000000.png", data)
        return Setup(["jbf-expand", r, "--image", f["image"], "--fx", "40", "--fy", "40",
                      "-o", OUT(tmp)])  # fmt: skip


for _name, (_data, _match) in BAD_DEPTHS.items():
    _viz_depth_case(_name, _data, _match)


@case("viz/depth-npy-garbage", match="not a readable .npy")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.npy", b"\x93NUMPY\x01\x00garbage")
    return Setup(["viz", d, "-o", OUT(tmp) / "v.png"])


@case("viz/depth-image-size-mismatch", match="--image: is (32, 64) but depths[0] is (16, 32)")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    img = write(IN(tmp) / "i.png", png_bytes(rgb_image()))
    return Setup(["viz", d, "--image", img, "-o", OUT(tmp) / "v.png"])


@case("viz/out-parent-is-a-file", match="a file is in the way")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    write(OUT(tmp) / "file", "x")
    return Setup(["viz", d, "-o", OUT(tmp) / "file" / "v.png"])


@case("viz/out-uncreatable", match="cannot create output folder")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(["viz", d, "-o", UNCREATABLE / "v.png"], out=tmp / "nothing")


@case("viz/out-is-the-input-depth", match="input")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(["viz", d, "--overwrite", "-o", d], out=IN(tmp))


@case("viz/out-is-the-input-image", match="input")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    img = write(IN(tmp) / "i.png", png_bytes(rgb_image()))
    return Setup(["viz", d, "--image", img, "--overwrite", "-o", img], out=IN(tmp))


@case("viz/out-suffix-not-image", expect="usage", match=".png or .jpg")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(["viz", d, "-o", OUT(tmp) / "v.txt"])


@case("stats/folder-without-depth", match="no depth maps")
def _(tmp):
    write(IN(tmp) / "d" / "notes.txt", "x")
    return Setup(["stats", IN(tmp) / "d"], out=tmp / "nothing")


@case("stats/reference-size-mismatch", match="its reference")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", depth_png_bytes(depth_map()))
    r = write(IN(tmp) / "r" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    return Setup(["stats", d, "--reference", r], out=tmp / "nothing")


@case("stats/npy-header-declares-huge-shape", match="truncated or corrupt")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.npy", npy_huge_header(10**7, 10**6))
    return Setup(["stats", d], out=tmp / "nothing")


@case("viz/npy-header-declares-huge-shape", match="truncated or corrupt")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.npy", npy_huge_header(10**7, 10**6))
    return Setup(["viz", d, "-o", OUT(tmp) / "v.png"])


@case("dataset-build/gt-npy-header-declares-huge-shape", match="truncated or corrupt")
def _(tmp):
    args = _build(tmp, "--gt", IN(tmp) / "gt")
    (IN(tmp) / "gt" / "000000.png").unlink()
    write(IN(tmp) / "gt" / "000000.npy", npy_huge_header(10**7, 10**6))
    return Setup(args)


@case("stats/npy-object-array", match=".npy")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.npy", npy_bytes(np.array([None, 1], dtype=object)))
    return Setup(["stats", d], out=tmp / "nothing")


# ======================================================================================
# jbf-expand (other than bad images / radar depth above)
# ======================================================================================


def _jbf(tmp, *extra, radar=None):
    f = good_frame(IN(tmp))
    r = radar or write(IN(tmp) / "radar" / "000000.png", depth_png_bytes(depth_map(density=0.02)))
    return ["jbf-expand", r, "--image", f["image"], *(extra or ("--fx", "40", "--fy", "40")),
            "-o", OUT(tmp)]  # fmt: skip


@case("jbf-expand/radar-image-size-mismatch", match="must have the same size")
def _(tmp):
    r = write(IN(tmp) / "radar" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    return Setup(_jbf(tmp, radar=r))


@case("jbf-expand/radar-pcd-truncated", match="truncated")
def _(tmp):
    r = write(IN(tmp) / "radar" / "000000.pcd", radar_pcd_bytes(20, declared=100))
    c = write(IN(tmp) / "cr" / "000000.json", json.dumps(json_calib()))
    return Setup(_jbf(tmp, "--calib", c, radar=r))


@case("jbf-expand/calib-json-garbage", match="not valid JSON")
def _(tmp):
    c = write(IN(tmp) / "cr" / "000000.json", b'{"K": [')
    return Setup(_jbf(tmp, "--calib", c))


@case("jbf-expand/lidar-8-bit", match="8-bit")
def _(tmp):
    lid = write(IN(tmp) / "lidar" / "000000.png", png_bytes(np.full((H, W), 9, np.uint8)))
    return Setup(_jbf(tmp, "--fx", "40", "--fy", "40", "--lidar", lid))


@case("jbf-expand/fx-without-fy", expect="usage", match="--fx")
def _(tmp):
    return Setup(_jbf(tmp, "--fx", "40"))


_out_cases(
    "jbf-expand",
    lambda tmp, out: [
        "jbf-expand",
        write(IN(tmp) / "radar" / "000000.png", depth_png_bytes(depth_map(density=0.02))).parent,
        "--image",
        good_frame(IN(tmp))["image"],
        "--fx",
        "40",
        "--fy",
        "40",
        "-o",
        out if out is not None else IN(tmp) / "radar" / "jbf",
    ],
)


# ======================================================================================
# dataset build / info / verify
# ======================================================================================


def _build(tmp, *extra, rgb=None, sparse=None):
    f = good_frame(IN(tmp))
    return ["dataset", "build", "--rgb", rgb or f["image"].parent, "--sparse",
            sparse or f["depth"].parent, *extra, "-o", OUT(tmp)]  # fmt: skip


def _dataset_depth_case(name, data, match):
    @case(f"dataset-build/sparse-{name}", match=match)
    def build(tmp):
        good_frame(IN(tmp))
        write(IN(tmp) / "depth" / "000000.png", data)
        return Setup(_build(tmp))

    @case(f"dataset-build/gt-{name}", match=match)
    def build2(tmp):
        f = good_frame(IN(tmp))
        write(f["gt"], data)
        return Setup(_build(tmp, "--gt", f["gt"].parent))


for _name, (_data, _match) in BAD_DEPTHS.items():
    _dataset_depth_case(_name, _data, _match)


@case("dataset-build/sparse-size-mismatch", match="sparse depth is 32x16")
def _(tmp):
    good_frame(IN(tmp))
    write(IN(tmp) / "depth" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    return Setup(_build(tmp))


@case("dataset-build/calib-size-mismatch", match="calibration is for")
def _(tmp):
    c = write(IN(tmp) / "cal" / "000000.json", json.dumps(json_calib(width=100, height=50)))
    return Setup(_build(tmp, "--calib", c.parent))


@case("dataset-build/calib-missing-key", match="missing key")
def _(tmp):
    c = write(IN(tmp) / "cal" / "000000.txt", kitti_calib_text(drop="P2"))
    return Setup(_build(tmp, "--calib", c.parent))


@case("dataset-build/sparse-table-garbage", match="cannot read the sparse-points table")
def _(tmp):
    t = write(IN(tmp) / "sparse.parquet", b"PAR1" + b"\x00" * 50 + b"PAR1")
    return Setup(_build(tmp, sparse=t))


@case("dataset-build/out-not-a-dataset", match="not a sparsetools dataset")
def _(tmp):
    write(OUT(tmp) / "holiday.jpg", b"x")
    return Setup(_build(tmp))


@case("dataset-build/out-manifest-garbage", match="manifest")
def _(tmp):
    write(OUT(tmp) / "manifest.parquet", b"not parquet at all")
    return Setup(_build(tmp))


@case("dataset-build/params-file-not-utf8", expect="usage", match="JSON")
def _(tmp):
    p = write(IN(tmp) / "params.json", b"\xff\xfe\x00{")
    return Setup(_build(tmp, "--params", p))


@case("dataset-build/split-file-binary", match="cannot read split file")
def _(tmp):
    s = write(IN(tmp) / "train.txt", b"\xff\xfe\x00\x00garbage")
    return Setup(_build(tmp, "--split-file", s))


@case("dataset-build/split-fractions-bad", expect="usage", match="split fractions as numbers")
def _(tmp):
    return Setup(_build(tmp, "--splits", "0.5,abc"))


@case("dataset-build/rgb-and-sparse-do-not-match", match="no frame has all its inputs")
def _(tmp):
    args = _build(tmp)
    (IN(tmp) / "depth" / "000000.png").rename(IN(tmp) / "depth" / "777777.png")
    return Setup(args)


_out_cases(
    "dataset-build",
    lambda tmp, out: [*_build(tmp)[:-1], out if out is not None else IN(tmp) / "image_2" / "ds"],
)


@case("dataset-build/link-to-file-outside-inputs", expect="ok")
def _(tmp):
    # Inputs that are symlinks are read through; --link stores a regular file (a hard link
    # or a copy) under DATASET/rgb, and every manifest path stays inside the dataset.
    outside = good_frame(tmp / "elsewhere")
    good_frame(IN(tmp))
    (IN(tmp) / "image_2" / "000000.png").unlink()
    (IN(tmp) / "image_2" / "000000.png").symlink_to(outside["image"])

    def check(tmp, result):
        from sparsetools.io.dataset import read_manifest, resolve_in_dataset

        table, _ = read_manifest(OUT(tmp) / "manifest.parquet")
        for col in ("rgb_path", "sparse_path"):
            for rel in table.column(col).to_pylist():
                p = resolve_in_dataset(OUT(tmp), rel)
                assert not p.is_symlink() and p.is_file()
        assert (OUT(tmp) / "rgb" / "000000.png").read_bytes() == outside["image"].read_bytes()

    return Setup(_build(tmp, "--link"), check=check, allowed_outputs=("*",))


def _good_dataset(tmp) -> Path:
    from click.testing import CliRunner

    from sparsetools.cli.main import cli

    src = tmp / "src"
    good_frame(src)
    ds = IN(tmp) / "ds"
    r = CliRunner().invoke(cli, ["dataset", "build", "--rgb", str(src / "image_2"), "--sparse",
                                 str(src / "depth"), "--gt", str(src / "gt"), "-o", str(ds)])  # fmt: skip
    assert r.exit_code == 0, r.stderr
    return ds


for _sub in ("info", "verify"):

    @case(f"dataset-{_sub}/no-manifest", match="no such manifest")
    def _(tmp, _sub=_sub):
        (IN(tmp) / "ds").mkdir(parents=True)
        return Setup(["dataset", _sub, IN(tmp) / "ds"], out=tmp / "nothing")

    @case(f"dataset-{_sub}/manifest-random-bytes", match="cannot read the manifest")
    def _(tmp, _sub=_sub):
        write(IN(tmp) / "ds" / "manifest.parquet", bytes(range(256)) * 3)
        return Setup(["dataset", _sub, IN(tmp) / "ds"], out=tmp / "nothing")

    @case(f"dataset-{_sub}/manifest-truncated", match="manifest")
    def _(tmp, _sub=_sub):
        ds = _good_dataset(tmp)
        m = ds / "manifest.parquet"
        m.write_bytes(truncated(m.read_bytes(), 0.6))
        return Setup(["dataset", _sub, ds], out=tmp / "nothing")

    @case(f"dataset-{_sub}/manifest-path-escapes", match="not a plain relative path")
    def _(tmp, _sub=_sub):
        import pyarrow.parquet as pq

        ds = _good_dataset(tmp)
        m = ds / "manifest.parquet"
        table = pq.read_table(m)
        i = table.column_names.index("rgb_path")
        import pyarrow as pa

        table = table.set_column(i, "rgb_path", pa.array(["../../etc/passwd"] * table.num_rows))
        pq.write_table(table, m)
        return Setup(["dataset", _sub, ds], out=tmp / "nothing")


@case("dataset-verify/file-replaced-by-symlink-outside", match="1 problem")
def _(tmp):
    ds = _good_dataset(tmp)
    rgb = ds / "rgb" / "000000.png"
    copy = write(tmp / "outside" / "000000.png", rgb.read_bytes())  # same bytes, same hash
    rgb.unlink()
    rgb.symlink_to(copy)

    def check(tmp, result):
        assert "resolves outside the dataset" in result.stdout

    return Setup(["dataset", "verify", ds], out=tmp / "nothing", check=check)


@case("dataset-verify/dataset-reached-through-a-symlink", expect="ok")
def _(tmp):
    # The rule is about files leaving the dataset: the dataset folder itself may be a link.
    ds = _good_dataset(tmp)
    (IN(tmp) / "link").symlink_to(ds)

    def check(tmp, result):
        assert "no problem" in result.stdout

    return Setup(["dataset", "verify", IN(tmp) / "link"], out=tmp / "nothing", check=check)


@case("lowlight-synth/output-symlink-to-outside-not-followed", match="symbolic link")
def _(tmp):
    victim = write(tmp / "victim" / "keep.png", b"precious")
    OUT(tmp).mkdir()
    (OUT(tmp) / "000000.png").symlink_to(victim)

    def check(tmp, result):
        assert victim.read_bytes() == b"precious"
        assert (OUT(tmp) / "000000.png").is_symlink()

    return Setup([*_lowlight(tmp), "--overwrite"], check=check)


@case("dataset-verify/file-changed", match="problem")
def _(tmp):
    ds = _good_dataset(tmp)
    write(ds / "gt" / "000000.png", depth_png_bytes(depth_map(3)))

    def check(tmp, result):
        assert "has changed" in result.stdout

    return Setup(["dataset", "verify", ds], out=tmp / "nothing", check=check)


@case("dataset-verify/file-missing", match="problem")
def _(tmp):
    ds = _good_dataset(tmp)
    (ds / "sparse" / "000000.png").unlink()

    def check(tmp, result):
        assert "is missing" in result.stdout

    return Setup(["dataset", "verify", ds], out=tmp / "nothing", check=check)


# ======================================================================================
# train / eval
# ======================================================================================


@case("train/no-manifest", match="no such manifest")
def _(tmp):
    (IN(tmp) / "ds").mkdir(parents=True)
    return Setup(["train", IN(tmp) / "ds", "-o", OUT(tmp)])


@case("train/manifest-garbage", match="cannot read the manifest")
def _(tmp):
    write(IN(tmp) / "ds" / "manifest.parquet", b"PAR1garbagePAR1")
    return Setup(["train", IN(tmp) / "ds", "-o", OUT(tmp)])


@case("train/out-is-a-file", match="not a folder")
def _(tmp):
    ds = _good_dataset(tmp)
    write(OUT(tmp), "in the way")
    return Setup(["train", ds, "-o", OUT(tmp), "--max-steps", "1"])


@case("eval/checkpoint-random-bytes", match="not a readable torch checkpoint")
def _(tmp):
    ds = _good_dataset(tmp)
    ck = write(IN(tmp) / "best.pt", bytes(range(256)) * 4)
    return Setup(["eval", "--checkpoint", ck, ds, "--split", "train"], out=tmp / "nothing")


@case("eval/checkpoint-zip-truncated", match="not a readable torch checkpoint")
def _(tmp):
    ds = _good_dataset(tmp)
    ck = write(IN(tmp) / "best.pt", b"PK\x03\x04" + b"\x00" * 100)
    return Setup(["eval", "--checkpoint", ck, ds], out=tmp / "nothing")


@case("eval/pred-gt-size-mismatch", match="prediction is 32x16")
def _(tmp):
    write(IN(tmp) / "pred" / "000000.png", depth_png_bytes(depth_map(w=32, h=16)))
    write(IN(tmp) / "gt" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(["eval", "--pred", IN(tmp) / "pred", "--gt", IN(tmp) / "gt"], out=tmp / "none")


@case("eval/pred-8-bit", match="8-bit")
def _(tmp):
    write(IN(tmp) / "pred" / "000000.png", png_bytes(np.full((H, W), 9, np.uint8)))
    write(IN(tmp) / "gt" / "000000.png", depth_png_bytes(depth_map()))
    return Setup(["eval", "--pred", IN(tmp) / "pred", "--gt", IN(tmp) / "gt"], out=tmp / "none")


@case("eval/gt-corrupt", match="cannot decode")
def _(tmp):
    write(IN(tmp) / "pred" / "000000.png", depth_png_bytes(depth_map()))
    write(IN(tmp) / "gt" / "000000.png", corrupt_png())
    return Setup(["eval", "--pred", IN(tmp) / "pred", "--gt", IN(tmp) / "gt"], out=tmp / "none")


@case("eval/no-matching-stems", match="no prediction")
def _(tmp):
    write(IN(tmp) / "pred" / "000000.png", depth_png_bytes(depth_map()))
    write(IN(tmp) / "gt" / "111111.png", depth_png_bytes(depth_map()))
    return Setup(["eval", "--pred", IN(tmp) / "pred", "--gt", IN(tmp) / "gt"], out=tmp / "none")


# ======================================================================================
# synth-scene and pipeline
# ======================================================================================


@case("synth-scene/out-is-a-file", match="not a folder")
def _(tmp):
    write(OUT(tmp), "x")
    return Setup(["synth-scene", "-o", OUT(tmp), "--frames", "1", "--image-size", "32x16",
                  "--underwater-frames", "0"])  # fmt: skip


@case("synth-scene/out-not-empty", match="not empty")
def _(tmp):
    write(OUT(tmp) / "mine.txt", "x")
    return Setup(["synth-scene", "-o", OUT(tmp), "--frames", "1", "--image-size", "32x16",
                  "--underwater-frames", "0"])  # fmt: skip


@case("synth-scene/check-folder-without-scene-json", match="scene.json")
def _(tmp):
    (IN(tmp) / "scene").mkdir(parents=True)
    return Setup(["synth-scene", "-o", OUT(tmp), "--check", IN(tmp) / "scene"])


@case("synth-scene/check-scene-json-garbage", match="scene.json")
def _(tmp):
    write(IN(tmp) / "scene" / "scene.json", b"\x00\xff{")
    return Setup(["synth-scene", "-o", OUT(tmp), "--check", IN(tmp) / "scene"])


@case("synth-scene/image-size-zero", expect="usage", match="must be finite and > 0")
def _(tmp):
    return Setup(["synth-scene", "-o", OUT(tmp), "--image-size", "0x16"])


@case("synth-scene/out-uncreatable", match="cannot create")
def _(tmp):
    return Setup(["synth-scene", "-o", UNCREATABLE, "--frames", "1", "--image-size", "32x16",
                  "--underwater-frames", "0"], out=tmp / "nothing")  # fmt: skip


#: A failed pipeline run still writes its report of the steps done so far (documented).
# what a failed pipeline run leaves: its report of the failure, and the record saying it wrote it
REPORT = ("report.md", "steps.json", ".sparsetools/files/report.md.json",
          ".sparsetools/files/steps.json.json")  # fmt: skip


@case("pipeline/config-missing", match="no such pipeline config")
def _(tmp):
    return Setup(["pipeline", IN(tmp) / "nope.yaml", "-o", OUT(tmp)])


@case("pipeline/config-binary-garbage", match="cannot read the pipeline config")
def _(tmp):
    c = write(IN(tmp) / "c.yaml", bytes(range(256)))
    return Setup(["pipeline", c, "-o", OUT(tmp)])


@case("pipeline/config-toml-garbage", match="invalid config")
def _(tmp):
    c = write(IN(tmp) / "c.toml", "[[steps]\nrun = ")
    return Setup(["pipeline", c, "-o", OUT(tmp)])


@case("pipeline/config-without-steps", match="non-empty 'steps' list")
def _(tmp):
    c = write(IN(tmp) / "c.yaml", "name: x\nvars: {a: 1}\n")
    return Setup(["pipeline", c, "-o", OUT(tmp)])


@case("pipeline/config-unknown-command", match="No such command 'frobnicate'")
def _(tmp):
    # -q: no step progress on stderr. A failed run still writes the report so far (documented).
    c = write(IN(tmp) / "c.yaml", "steps:\n  - name: a\n    run: frobnicate --now\n")
    return Setup(["-q", "pipeline", c, "-o", OUT(tmp)], allowed_outputs=REPORT)


@case("pipeline/step-fails-on-bad-input", match="step 'bad' failed")
def _(tmp):
    d = write(IN(tmp) / "d" / "000000.png", corrupt_png())
    c = write(IN(tmp) / "c.yaml", f"steps:\n  - name: bad\n    run: stats {d}\n")
    return Setup(["-q", "pipeline", c, "-o", OUT(tmp)], allowed_outputs=REPORT)


@case("pipeline/config-unknown-variable", match="unknown variable")
def _(tmp):
    c = write(IN(tmp) / "c.yaml", "steps:\n  - name: a\n    run: stats ${nothing}\n")
    return Setup(["pipeline", c, "-o", OUT(tmp)])


# ======================================================================================
# defocus-synth
# ======================================================================================


def _dense_depth(tmp) -> Path:
    return write(IN(tmp) / "dense" / "000000.png", depth_png_bytes(depth_map(density=1.0)))


def _defocus(tmp, *extra, depth=None):
    f = good_frame(IN(tmp))
    d = depth if depth is not None else _dense_depth(tmp)
    return ["defocus-synth", f["image"], "--depth", d, *extra, "-o", OUT(tmp)]


def _defocus_image_case(name, fname, data, match):
    @case(f"defocus-synth/{name}", match=match)
    def build(tmp):
        bad = write(IN(tmp) / "img" / fname, data)
        return Setup(["defocus-synth", bad, "--depth", _dense_depth(tmp), "-o", OUT(tmp)])


for _name, (_fname, _data, _match) in BAD_IMAGES.items():
    _defocus_image_case(_name, _fname, _data, _match)


def _defocus_depth_case(name, data, match):
    @case(f"defocus-synth/{name}", match=match)
    def build(tmp):
        return Setup(_defocus(tmp, depth=write(IN(tmp) / "dep" / "000000.png", data)))


for _name, (_data, _match) in BAD_DEPTHS.items():
    _defocus_depth_case(_name, _data, _match)


@case("defocus-synth/depth-size-mismatch", match="depth map is 32x16")
def _(tmp):
    d = write(IN(tmp) / "dep" / "000000.png", depth_png_bytes(depth_map(w=32, h=16, density=1)))
    return Setup(_defocus(tmp, depth=d))


@case("defocus-synth/depth-with-holes", match="--missing-depth far")
def _(tmp):
    return Setup(_defocus(tmp, depth=good_frame(IN(tmp))["depth"]))  # 30 % valid


@case("defocus-synth/depth-with-holes-rendered-far", expect="ok")
def _(tmp):
    def check(tmp, result):
        for rel in ("000000.png", "radius/000000.npy", "records/000000.json", "manifest.parquet"):
            assert (OUT(tmp) / rel).is_file(), rel

    depth = good_frame(IN(tmp))["depth"]
    return Setup(_defocus(tmp, "--missing-depth", "far", depth=depth), check=check)


@case("defocus-synth/depth-npy-garbage", match="not a readable .npy")
def _(tmp):
    return Setup(_defocus(tmp, depth=write(IN(tmp) / "dep" / "000000.npy", b"\x93NUMPY" * 9)))


@case("defocus-synth/depth-npy-huge-header", match="000000.npy")
def _(tmp):
    d = write(IN(tmp) / "dep" / "000000.npy", npy_huge_header(rows=10**6, cols=10**6))
    return Setup(_defocus(tmp, depth=d))


@case("defocus-synth/depth-folder-missing-frame", match="no depth map")
def _(tmp):
    write(IN(tmp) / "dep" / "999999.png", depth_png_bytes(depth_map(density=1.0)))
    return Setup(_defocus(tmp, depth=IN(tmp) / "dep"))


@case("defocus-synth/calib-non-numeric", match="non-numeric")
def _(tmp):
    c = write(IN(tmp) / "cal" / "000000.txt", kitti_calib_text().replace("P2: ", "P2: x ", 1))
    return Setup(_defocus(tmp, "--calib", c))


@case("defocus-synth/focus-inside-the-lens", match="must exceed the focal length")
def _(tmp):
    return Setup(_defocus(tmp, "--focal-length-mm", "50", "--focus-distance", "0.02"))


@case("defocus-synth/corrupt-record-sidecar-in-out", match="has no record of what made it")
def _(tmp):
    write(OUT(tmp) / "records" / "000000.json", b'{"record": ')
    return Setup(_defocus(tmp))


@case("defocus-synth/unknown-sensor-preset", expect="usage", match="nope")
def _(tmp):
    return Setup(_defocus(tmp, "--sensor", "nope"))


@case("defocus-synth/calib-and-focal-length", expect="usage", match="not both")
def _(tmp):
    return Setup(_defocus(tmp, "--calib", good_frame(IN(tmp))["calib"], "--focal-length-mm", "4"))


@case("defocus-synth/focus-range-inverted", expect="usage", match="inverted")
def _(tmp):
    return Setup(_defocus(tmp, "--focus-distance", "9,2"))


_out_cases(
    "defocus-synth",
    lambda tmp, out: [
        "defocus-synth",
        good_frame(IN(tmp))["image"].parent,
        "--depth",
        _dense_depth(tmp).parent,
        "-o",
        out if out is not None else IN(tmp) / "image_2" / "defocus",
    ],
)


# ======================================================================================
# dark-channel
# ======================================================================================

for _name, (_fname, _data, _match) in BAD_IMAGES.items():
    _image_case("dark-channel", _name, _fname, _data, _match)


@case("dark-channel/window-even", expect="usage", match="odd")
def _(tmp):
    return Setup(["dark-channel", good_frame(IN(tmp))["image"], "--window", "4", "-o", OUT(tmp)])


@case("dark-channel/mask-threshold-negative", expect="usage", match=">= 0")
def _(tmp):
    f = good_frame(IN(tmp))
    return Setup(["dark-channel", f["image"], "--mask-threshold", "-0.1", "-o", OUT(tmp)])


@case("dark-channel/foreign-file-in-out", match="has no record of what made it")
def _(tmp):
    write(OUT(tmp) / "mask" / "000000.png", png_bytes(rgb_image()))
    return Setup(["dark-channel", good_frame(IN(tmp))["image"], "-o", OUT(tmp)])


@case("dark-channel/grey-image-is-read-as-rgb", expect="ok")
def _(tmp):
    img = write(IN(tmp) / "img" / "000000.png", png_bytes(np.full((H, W), 90, np.uint8)))

    def check(tmp, result):
        import cv2

        dark = cv2.imread(str(OUT(tmp) / "dark" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert dark.shape == (H, W) and (dark == 90).all()

    return Setup(["dark-channel", img, "-o", OUT(tmp)], check=check)


_out_cases(
    "dark-channel",
    lambda tmp, out: [
        "dark-channel",
        good_frame(IN(tmp))["image"].parent,
        "-o",
        out if out is not None else IN(tmp) / "image_2" / "dc",
    ],
)


# ======================================================================================
# densify
# ======================================================================================


def _densify(tmp, *extra, sparse=None):
    f = good_frame(IN(tmp))
    return ["densify", sparse or f["depth"].parent, *extra, "-o", OUT(tmp)]


def _densify_depth_case(name, fname, data, match):
    @case(f"densify/{name}", match=match)
    def build(tmp):
        good_frame(IN(tmp))
        return Setup(_densify(tmp, sparse=write(IN(tmp) / "sp" / fname, data)))


for _name, (_data, _match) in BAD_DEPTHS.items():
    _densify_depth_case(_name, "000000.png", _data, _match)
_densify_depth_case("npy-garbage", "000000.npy", b"\x93NUMPY garbage" * 10, ".npy")
_densify_depth_case("npy-3d", "000000.npy", npy_bytes(np.zeros((2, 3, 4), np.float32)), "(H, W)")


@case("densify/max-depth-too-small", match="--inversion-offset: must be a finite number > 0.2")
def _(tmp):
    return Setup(_densify(tmp, "--inversion-offset", "0.1"))


@case("densify/unknown-method", expect="usage", match="--method")
def _(tmp):
    return Setup(_densify(tmp, "--method", "kriging"))


@case("densify/folder-without-depth-maps", match="no *.png/*.npy files in")
def _(tmp):
    write(IN(tmp) / "sp" / "notes.txt", "x")
    return Setup(_densify(tmp, sparse=IN(tmp) / "sp"))


@case("densify/empty-map-gives-zeros", expect="ok")
def _(tmp):
    d = write(IN(tmp) / "sp" / "000000.png", depth_png_bytes(np.zeros((H, W), np.float32)))

    def check(tmp, result):
        import cv2

        dense = cv2.imread(str(OUT(tmp) / "000000.png"), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(OUT(tmp) / "mask" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert dense.shape == (H, W) and not dense.any() and not mask.any()

    return Setup(_densify(tmp, sparse=d), check=check)


_out_cases(
    "densify",
    lambda tmp, out: [
        "densify",
        good_frame(IN(tmp))["depth"].parent,
        "-o",
        out if out is not None else IN(tmp) / "depth" / "dense",
    ],
)


# ======================================================================================
# accumulate
# ======================================================================================


def _identity_poses(n: int) -> str:
    return "1 0 0 0 0 1 0 0 0 0 1 0\n" * n


def _accumulate(tmp, *extra, poses=None, calib=True, out=None):
    """Two frames (000000, 000001) of good_frame clouds, identity poses, window 1."""
    good_frame(IN(tmp))
    good_frame(IN(tmp), "000001", seed=1)
    p = poses if poses is not None else write(IN(tmp) / "poses_velodyne.txt", _identity_poses(2))
    args = ["accumulate", IN(tmp) / "velodyne", "--image-size", f"{W}x{H}", "--window", "1"]
    if calib:
        args += ["--calib", IN(tmp) / "calib"]
    if p is not False:
        args += ["--poses", p]
    return [*args, *extra, "-o", out if out is not None else OUT(tmp)]


@case("accumulate/no-poses", match="no pose for frame 000000")
def _(tmp):
    return Setup(_accumulate(tmp, poses=False))


POSE_FILES = {
    "poses-non-numeric": ("1 0 0 0 0 1 0 0 0 0 1 x\n" * 2, "'x' is not a number"),
    "poses-wrong-count": ("1 0 0 0 0 1 0 0 0 0 1\n" * 2, "11 values"),
    "poses-not-rigid": ("2 0 0 0 0 1 0 0 0 0 1 0\n" * 2, "not a rigid transform"),
    "poses-nan": ("1 0 0 nan 0 1 0 0 0 0 1 0\n" * 2, "non-finite"),
    "poses-too-short": (_identity_poses(1), "frame 000001 needs line 2"),
    "poses-binary": ("\udcff", "not a text poses file"),
}


def _pose_file_case(name, text, match):
    @case(f"accumulate/{name}", match=match)
    def build(tmp):
        data = b"\xff\xfe\x00garbage" if text == "\udcff" else text
        return Setup(_accumulate(tmp, poses=write(IN(tmp) / "poses_velodyne.txt", data)))


for _name, (_text, _match) in POSE_FILES.items():
    _pose_file_case(_name, _text, _match)


@case("accumulate/truncated-cloud-in-a-window", match="not a multiple of 16")
def _(tmp):
    args = _accumulate(tmp)
    write(IN(tmp) / "velodyne" / "000001.bin", cloud().tobytes()[: 16 * 100 + 7])
    return Setup(args)


@case("accumulate/calib-missing-key", match="missing key 'Tr_velo_to_cam'")
def _(tmp):
    args = _accumulate(tmp)
    write(IN(tmp) / "calib" / "000000.txt", kitti_calib_text(drop="Tr_velo_to_cam"))
    return Setup(args)


@case("accumulate/no-calibration", match="--calib: no calibration for frame 000000")
def _(tmp):
    return Setup(_accumulate(tmp, calib=False))


@case("accumulate/mask-size-mismatch", match="mask is 32x16")
def _(tmp):
    write(IN(tmp) / "mask" / "000000.png", png_bytes(np.zeros((16, 32), np.uint8)))
    write(IN(tmp) / "mask" / "000001.png", png_bytes(np.zeros((16, 32), np.uint8)))
    return Setup(_accumulate(tmp, "--mask", IN(tmp) / "mask"))


@case("accumulate/mask-corrupt", match="cannot decode")
def _(tmp):
    write(IN(tmp) / "mask" / "000000.png", corrupt_png())
    write(IN(tmp) / "mask" / "000001.png", png_bytes(np.zeros((H, W), np.uint8)))
    return Setup(_accumulate(tmp, "--mask", IN(tmp) / "mask"))


@case("accumulate/mask-missing-a-frame", match="no mask for frame 000001")
def _(tmp):
    write(IN(tmp) / "mask" / "000000.png", png_bytes(np.zeros((H, W), np.uint8)))
    return Setup(_accumulate(tmp, "--mask", IN(tmp) / "mask"))


@case("accumulate/icp-on-a-nearly-empty-scan", match="ICP needs at least 10")
def _(tmp):
    args = _accumulate(tmp, poses=False)
    write(IN(tmp) / "velodyne" / "000001.bin", cloud(5).tobytes())
    return Setup([*args[:-2], "--icp", *args[-2:]])


@case("accumulate/poses-and-icp", expect="usage", match="give --poses or --icp, not both")
def _(tmp):
    args = _accumulate(tmp)
    return Setup([*args[:-2], "--icp", *args[-2:]])


@case("accumulate/window-beyond-the-sequence-is-clipped", expect="ok")
def _(tmp):
    def check(tmp, result):
        assert "every window is clipped to frames 000000..000001" in result.stderr
        assert (OUT(tmp) / "000000.png").is_file() and (OUT(tmp) / "000001.png").is_file()

    args = _accumulate(tmp)
    i = args.index("--window")
    args[i + 1] = "9"
    return Setup(args, check=check)


_out_cases(
    "accumulate",
    lambda tmp, out: _accumulate(tmp, out=out if out is not None else IN(tmp) / "velodyne" / "acc"),
)


if sys.platform != "linux":  # pragma: no cover - /sys is Linux-only
    CASES[:] = [c for c in CASES if "uncreatable" not in c.id]
