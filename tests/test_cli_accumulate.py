"""``sparsetools accumulate``: exact-pose videos against the library, pose sources (pose files,
camera poses, KITTI oxts, nuScenes ego poses, ICP), windows, resume, workers, bad input."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.calib import load_calibration
from sparsetools.io.pointcloud import read_points
from sparsetools.io.poses import read_kitti_poses
from sparsetools.ops.accumulate import AccumulateSettings, accumulate_scans
from sparsetools.ops.projection import project_points

W, H = 208, 64
N_FRAMES = 5
SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def summary_of(result) -> dict:
    assert result.exit_code == 0, (result.stdout, result.stderr)
    return json.loads(result.stdout)


def error_lines(result):
    return [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.startswith("WARNING:")]


def assert_clean_failure(result, code, match):
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    if code == 1:
        lines = error_lines(result)
        assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
        assert match in lines[0], lines[0]
    else:
        assert match in result.stderr, result.stderr


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def png_values(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.dtype == np.uint16, path
    return img


def kitti_png(depth: np.ndarray) -> np.ndarray:
    """KITTI's uint16 encoding, written out here: rint(d * 256) clipped to 1..65535, 0 empty."""
    q = np.clip(np.rint(depth.astype(np.float64) * 256.0), 1, 65535)
    return np.where(depth > 0, q, 0).astype(np.uint16)


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("video") / "video"
    r = run("synth-scene", "-o", out, "--video", "--static", "--sequences", 2, "--frames", N_FRAMES,
            "--image-size", f"{W}x{H}", "--seed", 3)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    return out


def sequence(video: Path, seq: str):
    """Scans, exact Velodyne poses and calibration of one synthetic sequence, read directly."""
    root = video / seq
    names = sorted(p.stem for p in (root / "velodyne").glob("*.bin"))
    scans = [read_points(root / "velodyne" / f"{n}.bin") for n in names]
    poses = read_kitti_poses(root / "poses_velodyne.txt")
    calib = load_calibration(root / "calib" / f"{names[0]}.txt").with_size(W, H)
    return names, scans, poses, calib


def library_map(scans, poses, calib, t, k, settings=None, mask=None):
    lo, hi = max(0, t - k), min(len(scans), t + k + 1)
    res = accumulate_scans(scans[lo:hi], poses[lo:hi], calib, reference=t - lo,
                           settings=settings, moving_mask=mask)  # fmt: skip
    return res


# -- the summary: one line, -v per frame (tests/test_plots.py) ------------------------------------


# -- exact poses ----------------------------------------------------------------------------------


def test_exact_poses_give_the_library_map_and_windows_stay_in_their_sequence(video, tmp_path):
    out = tmp_path / "acc"
    s = summary_of(run("accumulate", video, "-o", out, "--neighbours", 2, "--json"))
    assert s["frames"] == s["processed"] == 2 * N_FRAMES and s["failed"] == 0
    assert s["pose_source"] == "synthetic-video" and s["window"] == 2
    # frames 0, 1, 3, 4 of each sequence have clipped windows, and say so
    assert s["clipped_windows"] == 8
    assert s["clipped_window_frames"]["seq_0000/0000000000"] == "0000000000..0000000002"
    totals = dict.fromkeys(s["removed"], 0)
    for seq in ("seq_0000", "seq_0001"):
        names, scans, poses, calib = sequence(video, seq)
        for t, name in enumerate(names):
            res = library_map(scans, poses, calib, t, 2)
            got = png_values(out / seq / f"{name}.png")
            np.testing.assert_array_equal(got, kitti_png(res.depth))
            meta = json.loads((out / "calib" / seq / f"{name}.json").read_text())
            lo, hi = max(0, t - 2), min(N_FRAMES, t + 3)
            assert meta["window"] == [f"{seq}/{n}" for n in names[lo:hi]]
            assert all(f"/{seq}/velodyne/" in c for c in meta["cloud"])
            per = s["removed_per_frame"][f"{seq}/{name}"]
            assert per == {"occluded": res.counts.occluded,
                           "inconsistent": res.counts.inconsistent, "masked": 0}  # fmt: skip
            for reason in totals:
                totals[reason] += getattr(res.counts, reason)
    assert s["removed"] == totals and totals["occluded"] > 0
    # more pixels than the single scan (which covers 57 % of this small image already)
    names, scans, _, calib = sequence(video, "seq_0000")
    single = np.count_nonzero(project_points(scans[2], calib))
    assert np.count_nonzero(png_values(out / "seq_0000" / f"{names[2]}.png")) > 1.05 * single


def test_camera_poses_file_matches_the_velodyne_poses(video, tmp_path):
    """KITTI odometry style camera poses, converted with Tr_velo_to_cam, give the same maps."""
    seq = video / "seq_0000"
    args = [
        seq / "velodyne",
        "--calib",
        seq / "calib",
        "--image",
        seq / "image_2",
        "--neighbours",
        1,
    ]
    a = summary_of(run("accumulate", *args, "--poses", seq / "poses.txt", "-o", tmp_path / "cam",
                       "--json"))  # fmt: skip
    b = summary_of(run("accumulate", *args, "--poses", seq / "poses_velodyne.txt", "-o",
                       tmp_path / "velo", "--json"))  # fmt: skip
    assert a["pose_source"] == b["pose_source"] == "poses-file" and a["frames"] == N_FRAMES
    for name in (f"{i:010d}" for i in range(N_FRAMES)):  # flat input: OUT/<frame>.png
        x, y = (
            png_values(tmp_path / "cam" / f"{name}.png"),
            png_values(tmp_path / "velo" / f"{name}.png"),
        )
        assert np.mean(x == y) > 0.999, name  # the pose products differ in the last bits
    # --poses-frame sensor on the camera file would be wrong: it must change the maps
    c = run("accumulate", *args, "--poses", seq / "poses.txt", "--poses-frame", "sensor",
            "-o", tmp_path / "wrong")  # fmt: skip
    assert c.exit_code == 0
    name = f"{2:010d}"
    assert (
        np.mean(
            png_values(tmp_path / "wrong" / f"{name}.png")
            == png_values(tmp_path / "velo" / f"{name}.png")
        )
        < 0.99
    )


def test_mask_drops_the_other_scans_points(video, tmp_path):
    seq = video / "seq_0000"
    masks = tmp_path / "masks"
    masks.mkdir()
    mask = np.zeros((H, W), bool)
    mask[:, : W // 2] = True
    for i in range(N_FRAMES):
        cv2.imwrite(str(masks / f"{i:010d}.png"), mask.astype(np.uint8) * 255)
    s = summary_of(run("accumulate", seq / "velodyne", "--calib", seq / "calib", "--image",
                       seq / "image_2", "--poses", seq / "poses_velodyne.txt", "--mask", masks,
                       "--neighbours", 1, "-o", tmp_path / "acc", "--json"))  # fmt: skip
    names, scans, poses, calib = sequence(video, "seq_0000")
    for t, name in enumerate(names):
        res = library_map(scans, poses, calib, t, 1, mask=mask)
        np.testing.assert_array_equal(png_values(tmp_path / "acc" / f"{name}.png"),
                                      kitti_png(res.depth))  # fmt: skip
        assert s["removed_per_frame"][name]["masked"] == res.counts.masked > 0
    # in the masked half, only frame t's own points remain
    own = library_map(scans, poses, calib, 2, 0).depth
    got = png_values(tmp_path / "acc" / f"{names[2]}.png")
    np.testing.assert_array_equal(got[:, : W // 2], kitti_png(own)[:, : W // 2])


# -- KITTI raw oxts and nuScenes ego poses ------------------------------------------------------


R_E = 6378137.0


def oxts_of(T_world_from_imu: np.ndarray, lat0: float) -> list[float]:
    """Invert the KITTI devkit conversion (Mercator at scale cos(lat0), R = Rz Ry Rx)."""
    s = math.cos(math.radians(lat0))
    R, t = T_world_from_imu[:3, :3], T_world_from_imu[:3, 3]
    lon = math.degrees(t[0] / (s * R_E))
    lat = math.degrees(2 * math.atan(math.exp(t[1] / (s * R_E)))) - 90.0
    yaw, pitch = math.atan2(R[1, 0], R[0, 0]), -math.asin(R[2, 0])
    roll = math.atan2(R[2, 1], R[2, 2])
    return [lat, lon, float(t[2]), roll, pitch, yaw] + [0.0] * 19 + [4, 11, 6, 6, 6]


def kv(name: str, values) -> str:
    return f"{name}: " + " ".join(repr(float(v)) for v in np.ravel(values)) + "\n"


def test_kitti_raw_oxts_poses(video, tmp_path):
    """A KITTI raw drive made of the synthetic sequence, its oxts written from the exact poses
    through an IMU mounted 0.8 m behind the Velodyne: the oxts poses rebuild the same maps."""
    names, scans, poses, calib = sequence(video, "seq_0000")
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync"
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    (drive / "oxts" / "data").mkdir(parents=True)
    T_velo_from_imu = np.eye(4)
    T_velo_from_imu[:3, 3] = [-0.81, 0.32, -0.8]
    # the oxts world: east-north-up (camera z -> east, x -> south, y -> down) near 49 deg N
    T_enu = np.eye(4)
    T_enu[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    y49 = R_E * math.cos(math.radians(49)) * math.log(math.tan(math.radians(139) / 2))
    T_enu[:3, 3] = [1000.0, y49, 110.0]
    lat0 = 49.0
    for _ in range(3):  # the devkit's scale is cos(latitude of the first packet)
        lat0 = oxts_of(T_enu @ poses[0] @ T_velo_from_imu, lat0)[0]
    P = np.hstack([calib.K, np.zeros((3, 1))])
    (date / "calib_cam_to_cam.txt").write_text(
        kv("P_rect_02", P) + kv("R_rect_00", np.eye(3)) + kv("S_rect_02", [W, H])
    )
    T_cv = calib.T_cam_from_sensor
    (date / "calib_velo_to_cam.txt").write_text(kv("R", T_cv[:3, :3]) + kv("T", T_cv[:3, 3]))
    (date / "calib_imu_to_velo.txt").write_text(
        kv("R", T_velo_from_imu[:3, :3]) + kv("T", T_velo_from_imu[:3, 3]))  # fmt: skip
    for name, T in zip(names, poses, strict=True):
        shutil.copy(
            video / "seq_0000" / "velodyne" / f"{name}.bin", drive / "velodyne_points" / "data"
        )
        packet = oxts_of(T_enu @ T @ T_velo_from_imu, lat0)
        (drive / "oxts" / "data" / f"{name}.txt").write_text(" ".join(map(repr, packet)) + "\n")
    s = summary_of(run("accumulate", drive, "-o", tmp_path / "acc", "--neighbours", 2, "--json"))
    assert s["pose_source"] == "kitti-oxts" and s["frames"] == N_FRAMES
    for t, name in enumerate(names):
        expected = kitti_png(library_map(scans, poses, calib, t, 2).depth)
        got = png_values(tmp_path / "acc" / drive.name / f"{name}.png")
        assert np.mean(got == expected) > 0.999
    # frame 3's packet is an input of the frames whose window holds frame 3 (1..4 with K=2),
    # packet 0 (the Mercator scale and origin) of every frame
    p3 = drive / "oxts" / "data" / f"{names[3]}.txt"
    p3.write_text(p3.read_text().replace(" 4 11 6 6 6", " 4 12 6 6 6"))
    again = summary_of(
        run("accumulate", drive, "-o", tmp_path / "acc", "--neighbours", 2, "--json")
    )
    assert again["recomputed"] == 4 and again["skipped_existing"] == 1


def test_nuscenes_ego_poses_in_time_order(video, tmp_path):
    """LIDAR_TOP key frames of a nuScenes root: Frame.pose from the ego poses, windows in
    timestamp order (the sample tokens sort otherwise)."""
    from scipy.spatial.transform import Rotation

    names, scans, poses, calib = sequence(video, "seq_0000")
    root = tmp_path / "nus"
    (root / "v1.0-mini").mkdir(parents=True)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("z", 31, degrees=True).as_matrix()
    G[:3, 3] = [300.0, -120.0, 4.0]

    def quat(R):
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        return [w, x, y, z]

    T_ego_from_cam = np.linalg.inv(calib.T_cam_from_sensor)
    cs = [
        {
            "token": "cs-l",
            "sensor_token": "s-l",
            "rotation": [1, 0, 0, 0],
            "translation": [0, 0, 0],
            "camera_intrinsic": [],
        },
        {
            "token": "cs-c",
            "sensor_token": "s-c",
            "rotation": quat(T_ego_from_cam[:3, :3]),
            "translation": T_ego_from_cam[:3, 3].tolist(),
            "camera_intrinsic": calib.K.tolist(),
        },
    ]
    sensors = [{"token": "s-l", "channel": "LIDAR_TOP", "modality": "lidar"},
               {"token": "s-c", "channel": "CAM_FRONT", "modality": "camera"}]  # fmt: skip
    tokens = ["tok-d", "tok-b", "tok-e", "tok-a", "tok-c"]  # time order != token order
    samples, sds, eps = [], [], []
    for k, (tok, T) in enumerate(zip(tokens, poses, strict=True)):
        Tg = G @ T
        eps.append(
            {
                "token": f"ep-{k}",
                "rotation": quat(Tg[:3, :3]),
                "translation": Tg[:3, 3].tolist(),
                "timestamp": 10**6 * (k + 1),
            }
        )
        samples.append({"token": tok, "timestamp": 10**6 * (k + 1), "scene_token": "scene-x"})
        lidar = f"samples/LIDAR_TOP/{k}.pcd.bin"
        (root / lidar).parent.mkdir(parents=True, exist_ok=True)
        np.column_stack([scans[k], np.zeros(len(scans[k]))]).astype("<f4").tofile(root / lidar)
        cam = f"samples/CAM_FRONT/{k}.png"
        (root / cam).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(video / "seq_0000" / "image_2" / f"{names[k]}.png", root / cam)
        for ch, fn, c in (("l", lidar, "cs-l"), ("c", cam, "cs-c")):
            sds.append(
                {
                    "token": f"sd-{ch}{k}",
                    "sample_token": tok,
                    "ego_pose_token": f"ep-{k}",
                    "calibrated_sensor_token": c,
                    "filename": fn,
                    "is_key_frame": True,
                    "timestamp": 10**6 * (k + 1),
                    "prev": "",
                    "next": "",
                    "width": W,
                    "height": H,
                }
            )
    for name, rows in (("sample", samples), ("sample_data", sds), ("ego_pose", eps),
                       ("calibrated_sensor", cs), ("sensor", sensors)):  # fmt: skip
        (root / "v1.0-mini" / f"{name}.json").write_text(json.dumps(rows))
    s = summary_of(run("accumulate", root, "-o", tmp_path / "acc", "--neighbours", 1, "--json"))
    assert s["pose_source"] == "nuscenes" and s["frames"] == N_FRAMES
    for t, tok in enumerate(tokens):
        expected = kitti_png(library_map(scans, poses, calib, t, 1).depth)
        got = png_values(tmp_path / "acc" / "scene-x" / f"{tok}.png")
        assert np.mean(got == expected) > 0.999, tok
        meta = json.loads((tmp_path / "acc" / "calib" / "scene-x" / f"{tok}.json").read_text())
        assert meta["window"] == [f"scene-x/{x}" for x in tokens[max(0, t - 1) : t + 2]]


# -- resume and workers ---------------------------------------------------------------------------


def test_resume_changing_one_scan_recomputes_its_windows(video, tmp_path):
    data = tmp_path / "video"
    shutil.copytree(video / "seq_0000", data / "seq_0000")
    out = tmp_path / "acc"
    args = ["accumulate", data / "seq_0000", "-o", out, "--neighbours", 1, "--json"]
    first = summary_of(run(*args))
    assert first["processed"] == N_FRAMES
    again = summary_of(run(*args))
    assert again["processed"] == 0 and again["skipped_existing"] == N_FRAMES
    before = digest(out)
    refused = run(*args, "--occlusion-rel", 0.2)
    assert_clean_failure(refused, 1, "made with --occlusion-rel 0.1, not 0.2")
    assert digest(out) == before
    scan = data / "seq_0000" / "velodyne" / f"{2:010d}.bin"
    pts = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
    pts[:-1000].tofile(scan)
    redo = summary_of(run(*args))
    assert redo["recomputed"] == redo["processed"] == 3  # frames 1, 2, 3 hold frame 2
    changed = {k for k in digest(out) if digest(out)[k] != before.get(k)}
    assert {Path(k).stem for k in changed} <= {f"{i:010d}" for i in (1, 2, 3)}
    # the pose file is an input of every frame
    poses = data / "seq_0000" / "poses_velodyne.txt"
    lines = poses.read_text().splitlines()
    lines[4] = " ".join([*lines[4].split()[:11], "0.5"])
    poses.write_text("\n".join(lines) + "\n")
    redo = summary_of(run(*args))
    assert redo["recomputed"] == N_FRAMES


def test_two_workers_write_the_same_bytes(video, tmp_path):
    base = ["accumulate", video, "--neighbours", 1]
    assert run(*base, "-o", tmp_path / "a", "--workers", 1).exit_code == 0
    assert run(*base, "-o", tmp_path / "b", "--workers", 2).exit_code == 0
    a, b = digest(tmp_path / "a"), digest(tmp_path / "b")
    assert len(a) == 4 * N_FRAMES and a == b


# -- bad input --------------------------------------------------------------------------------------


def test_no_pose_for_a_frame(tmp_path):
    r = run("accumulate", SYNTH / "velodyne", "--calib", SYNTH / "calib", "--image-size",
            "1242x375", "-o", tmp_path / "out")  # fmt: skip
    assert_clean_failure(r, 1, "no pose for frame 000000")
    assert "--icp" in r.stderr and not (tmp_path / "out").exists()


def test_pose_file_shorter_than_the_sequence(video, tmp_path):
    seq = video / "seq_0000"
    short = tmp_path / "poses_velodyne.txt"
    short.write_text("".join((seq / "poses_velodyne.txt").read_text().splitlines(True)[:3]))
    r = run("accumulate", seq / "velodyne", "--calib", seq / "calib", "--image", seq / "image_2",
            "--poses", short, "-o", tmp_path / "out")  # fmt: skip
    assert_clean_failure(r, 1, "has 3 line(s); frame 0000000003 needs line 4")
    assert "2 of 5 frames" in r.stderr and not (tmp_path / "out").exists()


def test_one_pose_file_for_two_sequences(video, tmp_path):
    r = run("accumulate", video, "--poses", video / "seq_0000" / "poses.txt", "-o", tmp_path / "o")
    assert_clean_failure(r, 1, "one pose file but the frames are 2 sequences")


def test_missing_calibration(video, tmp_path):
    seq = video / "seq_0000"
    r = run(
        "accumulate", seq / "velodyne", "--poses", seq / "poses_velodyne.txt", "-o", tmp_path / "o"
    )
    assert_clean_failure(r, 1, "--calib: no calibration for frame 0000000000")
    assert not (tmp_path / "o").exists()


def test_window_larger_than_the_sequence_is_clipped_and_said(video, tmp_path):
    seq = video / "seq_0001"
    args = ["accumulate", seq, "-o", tmp_path / "acc", "--neighbours", 50, "--json"]
    r = CliRunner().invoke(cli, [str(a) for a in args])  # not quiet: the warning is the point
    s = summary_of(r)
    assert "fewer than the 101 of --neighbours 50" in r.stderr
    assert s["clipped_windows"] == N_FRAMES
    assert set(s["clipped_window_frames"].values()) == {"0000000000..0000000004"}
    names, scans, poses, calib = sequence(video, "seq_0001")
    expected = accumulate_scans(scans, poses, calib, reference=4).depth
    np.testing.assert_array_equal(png_values(tmp_path / "acc" / "seq_0001" / f"{names[4]}.png"),
                                  kitti_png(expected))  # fmt: skip


@pytest.mark.parametrize(
    "extra, code, match",
    [
        (["--icp", "--poses", "POSES"], 2, "give --poses or --icp, not both"),
        (["--icp-min-range", "20"], 2, "--icp-min-range goes with --icp"),
        (["--poses-frame", "camera"], 2, "--poses-frame goes with --poses"),
        (["--neighbours", "-1"], 2, "--neighbours"),
        (["--window", "-1"], 2, "--neighbours"),
        (["--min-radius-px", "5", "--max-radius-px", "2"], 2, "--max-radius-px"),
        (["--footprint-m", "0"], 2, "--footprint-m"),
    ],
)
def test_usage_errors(video, tmp_path, extra, code, match):
    extra = [str(video / "seq_0000" / "poses.txt") if e == "POSES" else e for e in extra]
    r = run("accumulate", video / "seq_0000", "-o", tmp_path / "o", *extra)
    assert_clean_failure(r, code, match)
    assert not (tmp_path / "o").exists()


def test_settings_record_every_accumulate_field(video, tmp_path):
    out = tmp_path / "acc"
    assert run("accumulate", video / "seq_0000", "-o", out, "--neighbours", 0).exit_code == 0
    record = json.loads((out / ".sparsetools" / "run.json").read_text())["settings"]
    fields = AccumulateSettings.__dataclass_fields__
    # occlude_own (0.4) is recorded only when set, so older folders resume.
    assert set(fields) - {"occlude_own"} <= set(record) and record["window"] == 0
    assert "occlude_own" not in record
    assert record["pose_source"] == "synthetic-video"
    # window 0 is the single scan's projection
    names, scans, _, calib = sequence(video, "seq_0000")
    np.testing.assert_array_equal(png_values(out / "seq_0000" / f"{names[1]}.png"),
                                  kitti_png(project_points(scans[1], calib)))  # fmt: skip


# -- ICP on the real KITTI sequence -----------------------------------------------------------------


@pytest.mark.real
def test_icp_on_three_real_kitti_frames(real_dir, tmp_path):
    from sparsetools.ops.registration import chain_poses

    drive = real_dir / "kitti-raw-sequence-2011_09_26"
    scans = [drive / "velodyne_points" / "data" / f"{i:010d}.bin" for i in range(3)]
    out = tmp_path / "acc"
    s = summary_of(run("accumulate", *scans, "--calib", drive, "--icp", "--icp-min-range", 20,
                       "--neighbours", 1, "-o", out, "--json"))  # fmt: skip
    assert s["pose_source"] == "icp" and s["frames"] == 3
    icp = s["icp"]
    assert icp["pairs"] == icp["computed"] == 2 and icp["failed"] == 0
    for pair in ("0000000001", "0000000002"):
        # measured: fitness 0.93-0.94, inlier RMSE 0.14-0.16 m (docs/accumulate.md)
        assert icp["per_pair"][pair]["fitness"] > 0.85
        assert 0 < icp["per_pair"][pair]["inlier_rmse_m"] < 0.25
        T = np.asarray(
            json.loads((out / "icp" / f"{pair}.json").read_text())["T_target_from_source"]
        )
        assert 0.1 < T[0, 3] < 0.4  # the car drives forward ~0.24 m per frame
    # the middle frame: the library on the same scans with the chained pair poses
    pairs = [np.asarray(json.loads((out / "icp" / f"{p}.json").read_text())["T_target_from_source"])
             for p in ("0000000001", "0000000002")]  # fmt: skip
    calib = load_calibration(drive)
    points = [read_points(p) for p in scans]
    res = accumulate_scans(points, chain_poses(pairs, reference=1), calib, reference=1)
    got = png_values(out / "0000000001.png")
    np.testing.assert_array_equal(got, kitti_png(res.depth))
    single = np.count_nonzero(project_points(points[1], calib))
    assert np.count_nonzero(got) > 1.8 * single  # measured: 2.2x with 3 scans
    again = summary_of(run("accumulate", *scans, "--calib", drive, "--icp", "--icp-min-range", 20,
                           "--neighbours", 1, "-o", out, "--json"))  # fmt: skip
    assert again["skipped_existing"] == 3 and again["icp"]["computed"] == 0
    assert again["icp"]["per_pair"] == icp["per_pair"]
