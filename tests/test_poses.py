"""Pose files (KITTI odometry poses.txt, 4x4 per frame, times.txt, KITTI raw oxts) and the
standard oxts -> pose conversion."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sparsetools.errors import FormatError, ParameterError
from sparsetools.io.poses import (
    EARTH_RADIUS_M,
    OXTS_FIELDS,
    OxtsPacket,
    oxts_poses,
    read_imu_to_velo,
    read_kitti_poses,
    read_oxts_folder,
    read_oxts_packet,
    read_pose_matrix,
    read_times,
    sensor_poses,
    write_kitti_poses,
    write_oxts_packet,
    write_pose_matrix,
    write_times,
)

DRIVE = "kitti-raw-2011_09_26-drive0001-text"
OXTS = f"{DRIVE}/2011_09_26_drive_0001_sync/2011_09_26/2011_09_26_drive_0001_sync/oxts"
IMU_TO_VELO = f"{DRIVE}/2011_09_26_calib/2011_09_26/calib_imu_to_velo.txt"


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """Rigid transforms from random unit quaternions (independent of the module's code)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((n, 4, 4))
    for i in range(n):
        q = rng.normal(size=4)
        w, x, y, z = q / math.sqrt(float(q @ q))
        out[i, :3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        out[i, :3, 3] = rng.uniform(-500, 500, 3)
        out[i, 3, 3] = 1.0
    return out


# -- round trips ---------------------------------------------------------------------------------
def test_kitti_poses_round_trip_bit_exact(tmp_path):
    poses = random_poses(7)
    write_kitti_poses(tmp_path / "poses.txt", poses)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    assert len(lines) == 7 and all(len(line.split()) == 12 for line in lines)
    # Row-major top 3x4, as KITTI odometry.
    assert [float(v) for v in lines[2].split()] == poses[2, :3].ravel().tolist()
    back = read_kitti_poses(tmp_path / "poses.txt")
    assert back.shape == (7, 4, 4) and np.array_equal(back, poses)


def test_pose_matrix_round_trip_and_empty_poses(tmp_path):
    T = random_poses(1, seed=3)[0]
    write_pose_matrix(tmp_path / "0000000000.txt", T)
    assert np.array_equal(read_pose_matrix(tmp_path / "0000000000.txt"), T)
    text = (tmp_path / "0000000000.txt").read_text().splitlines()
    assert len(text) == 4 and text[3].split() == ["0.0", "0.0", "0.0", "1.0"]
    write_kitti_poses(tmp_path / "empty.txt", np.zeros((0, 4, 4)))
    assert read_kitti_poses(tmp_path / "empty.txt").shape == (0, 4, 4)


def test_reads_kitti_odometry_precision(tmp_path):
    """KITTI's poses carry 6-7 digits (rotation orthonormal to ~1e-6): they are accepted."""
    T = random_poses(2, seed=5)
    (tmp_path / "p.txt").write_text(
        "".join(" ".join(f"{v:e}" for v in P[:3].ravel()) + "\n" for P in T)
    )
    back = read_kitti_poses(tmp_path / "p.txt")
    assert np.allclose(back, T, atol=1e-3)


def test_times_round_trip(tmp_path):
    t = np.arange(5) / 10.0
    write_times(tmp_path / "times.txt", t)
    assert (tmp_path / "times.txt").read_text().splitlines()[1] == "1.000000e-01"
    assert np.allclose(read_times(tmp_path / "times.txt"), t)
    (tmp_path / "bad.txt").write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(FormatError, match=r"bad\.txt:3"):
        read_times(tmp_path / "bad.txt")
    with pytest.raises(ParameterError):
        write_times(tmp_path / "x.txt", [0.0, np.nan])


def packet(**changes) -> OxtsPacket:
    base = dict.fromkeys(OXTS_FIELDS[:25], 0.0)
    base.update(
        lat=49.0, lon=8.4, alt=110.0, navstat=4, numsats=10, posmode=6, velmode=6, orimode=6
    )
    base.update(changes)
    return OxtsPacket(**base)


def test_oxts_packet_round_trip(tmp_path):
    p = packet(roll=0.01, pitch=-0.02, yaw=1.234567890123, vf=9.87654321, numsats=11)
    write_oxts_packet(tmp_path / "0000000000.txt", p)
    assert len((tmp_path / "0000000000.txt").read_text().split()) == 30
    assert read_oxts_packet(tmp_path / "0000000000.txt") == p
    assert len(OXTS_FIELDS) == 30 and OXTS_FIELDS[-5:] == (
        "navstat",
        "numsats",
        "posmode",
        "velmode",
        "orimode",
    )


# -- the real packet and calibration -------------------------------------------------------------
@pytest.mark.real
def test_real_oxts_packet_parses(real_dir):
    p = read_oxts_packet(real_dir / OXTS / "data" / "0000000000.txt")
    # Values from the file (README: lat 49.015003823272, lon 8.4342971002335, alt 116.43...).
    assert p.lat == 49.015003823272 and p.lon == 8.4342971002335
    assert p.alt == pytest.approx(116.43032836914)
    assert p.yaw == pytest.approx(-2.6087069803847)
    assert (p.navstat, p.numsats, p.posmode, p.velmode, p.orimode) == (4, 11, 6, 6, 6)
    # Forward speed from the velocities north/east: |(vn, ve)| ~ vf (the car drives level).
    assert math.hypot(p.vn, p.ve) == pytest.approx(p.vf, rel=0.01)
    packets = read_oxts_folder(real_dir / OXTS.rsplit("/", 1)[0])
    assert packets == [p]
    assert np.array_equal(oxts_poses(packets)[0], np.eye(4))


@pytest.mark.real
def test_real_imu_to_velo(real_dir):
    T = read_imu_to_velo(real_dir / IMU_TO_VELO)
    assert np.allclose(T[:3, 3], [-8.086759e-01, 3.195559e-01, -7.997231e-01])
    assert T[0, 0] == pytest.approx(9.999976e-01) and T[1, 2] == pytest.approx(-1.482298e-02)
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6)


# -- hand-computed drive -------------------------------------------------------------------------
def test_two_packet_drive_north_gives_known_translation():
    """Straight north at 10 m/s for 0.1 s (yaw = pi/2: heading north; 0 = east).

    Hand computation: the latitude step for 1 m north is 1 / R_e rad; the Mercator northing
    is ``s R_e atanh(sin(lat))`` with ``s = cos(lat0)`` (atanh(sin x) = log(tan(pi/4 + x/2))),
    so the IMU of packet 1 sits ``d = s R_e (atanh(sin lat1) - atanh(sin lat0))`` ahead
    (= 1 m to 1e-7) along its own x axis, with the same attitude.
    """
    lat0 = 49.0
    dlat = math.degrees(1.0 / EARTH_RADIUS_M)
    p0 = packet(lat=lat0, yaw=math.pi / 2, vn=10.0, vf=10.0)
    p1 = dataclasses.replace(p0, lat=lat0 + dlat)
    d = (
        math.cos(math.radians(lat0))
        * EARTH_RADIUS_M
        * (
            math.atanh(math.sin(math.radians(lat0 + dlat)))
            - math.atanh(math.sin(math.radians(lat0)))
        )
    )
    assert d == pytest.approx(1.0, abs=1e-6)
    T = oxts_poses([p0, p1])
    assert np.array_equal(T[0], np.eye(4))
    assert np.allclose(T[1][:3, :3], np.eye(3), atol=1e-12)
    assert np.allclose(T[1][:3, 3], [d, 0.0, 0.0], atol=1e-6)
    # pykitti's origin keeps the east-north-up axes: the same step shows as +y (north).
    E = oxts_poses([p0, p1], origin="first_position")
    assert np.allclose(E[1][:3, 3], [0.0, d, 0.0], atol=1e-6)
    assert np.allclose(E[1][:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_attitude_is_rz_ry_rx():
    roll, pitch, yaw = 0.1, -0.2, 0.3
    T = oxts_poses([packet(), packet(roll=roll, pitch=pitch, yaw=yaw)], origin="first_position")

    def rx(a):
        return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])

    def ry(a):
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    def rz(a):
        return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])

    assert np.allclose(T[1][:3, :3], rz(yaw) @ ry(pitch) @ rx(roll), atol=1e-15)
    # Positive pitch = front down: the IMU's x axis points below the horizon.
    assert T[1][2, 0] > 0 > oxts_poses([packet(pitch=0.1)], origin="first_position")[0][2, 0]


def test_velodyne_poses_from_imu():
    """T_world_velo = T_world_imu inv(T_velo_imu): a pure IMU translation moves the LiDAR the
    same way when the mounting has no rotation; relative_to_first makes pose 0 the identity."""
    T_wi = np.stack([np.eye(4), np.eye(4)])
    T_wi[1, :3, 3] = (2.0, 0.0, 0.0)
    T_vi = np.eye(4)
    T_vi[:3, 3] = (-0.8, 0.3, -0.8)  # IMU -> Velodyne
    P = sensor_poses(T_wi, T_vi)
    assert np.allclose(P[0][:3, 3], [0.8, -0.3, 0.8])  # the Velodyne in the IMU's world
    assert np.allclose(P[1][:3, 3] - P[0][:3, 3], [2.0, 0.0, 0.0])
    R = sensor_poses(T_wi, T_vi, relative_to_first=True)
    assert np.allclose(R[0], np.eye(4)) and np.allclose(R[1][:3, 3], [2.0, 0.0, 0.0])
    with pytest.raises(ParameterError, match="T_sensor_from_imu"):
        sensor_poses(T_wi, 2 * np.eye(4))


# -- rejection -----------------------------------------------------------------------------------
ROW = "1 0 0 0 0 1 0 0 0 0 1 0"


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        (f"{ROW}\n1 0 0 0 0 1 0 0 0 0 1\n", 2, "11 values"),
        (f"{ROW}\n1 0 0 0 0 1 0 0 0 0 1 x\n", 2, "not a number"),
        (f"{ROW}\n{ROW}\n1 0 0 nan 0 1 0 0 0 0 1 0\n", 3, "non-finite"),
        ("2 0 0 0 0 2 0 0 0 0 2 0\n", 1, "orthonormal"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0\n", 1, "reflection"),
        (f"{ROW}\n\n", 2, "0 values"),
    ],
)
def test_bad_poses_files(tmp_path, text, line, what):
    path = tmp_path / "poses.txt"
    path.write_text(text)
    with pytest.raises(FormatError) as err:
        read_kitti_poses(path)
    msg = str(err.value)
    assert f"poses.txt:{line}:" in msg and what in msg and "\n" not in msg


def test_bad_pose_matrix_files(tmp_path):
    path = tmp_path / "0000000000.txt"
    path.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(FormatError, match="3 lines"):
        read_pose_matrix(path)
    path.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n")
    with pytest.raises(FormatError, match=r"0000000000\.txt:4: .*last row"):
        read_pose_matrix(path)
    path.write_text("1 0 0 0\n0 1 0 0\n0 0 1 inf\n0 0 0 1\n")
    with pytest.raises(FormatError, match=r":3: non-finite"):
        read_pose_matrix(path)
    with pytest.raises(FormatError, match="no such"):
        read_pose_matrix(tmp_path / "missing.txt")


def test_writers_refuse_non_rigid(tmp_path):
    with pytest.raises(ParameterError, match="rigid"):
        write_pose_matrix(tmp_path / "a.txt", np.diag([1.0, 1.0, 2.0, 1.0]))
    bad = random_poses(3)
    bad[1, 0, 3] = np.inf
    with pytest.raises(ParameterError, match=r"poses\[1\]"):
        write_kitti_poses(tmp_path / "b.txt", bad)
    with pytest.raises(ParameterError, match="N, 4, 4"):
        write_kitti_poses(tmp_path / "c.txt", np.eye(4))
    assert not list(tmp_path.iterdir())


def test_bad_oxts_packets(tmp_path):
    path = tmp_path / "0000000000.txt"
    good = tmp_path / "good.txt"
    write_oxts_packet(good, packet())
    values = good.read_text().split()
    for text, what in [
        (" ".join(values[:29]), "29 values"),
        (" ".join([*values[:25], "4.5", *values[26:]]), "integers"),
        (" ".join(["95.0", *values[1:]]), "out of range"),
        (" ".join([*values[:3], "nan", *values[4:]]), "non-finite"),
        (" ".join(values) + "\n" + " ".join(values), "2 lines"),
        ("", "0 lines"),
    ]:
        path.write_text(text + "\n")
        with pytest.raises(FormatError) as err:
            read_oxts_packet(path)
        assert str(path) in str(err.value) and what in str(err.value), text
    with pytest.raises(FormatError, match="no oxts"):
        read_oxts_folder(tmp_path / "nowhere")


def test_bad_imu_to_velo(tmp_path):
    path = tmp_path / "calib_imu_to_velo.txt"
    path.write_text("calib_time: 25-May-2012 16:47:16\nR: 1 0 0 0 1 0 0 0 1\n")
    with pytest.raises(FormatError, match="missing key 'T'"):
        read_imu_to_velo(path)
    path.write_text("R: 1 0 0 0 1 0 0 0 3\nT: 0 0 0\n")
    with pytest.raises(FormatError, match=r"calib_imu_to_velo\.txt:1: R is not a rotation"):
        read_imu_to_velo(path)
    path.write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0\n")
    with pytest.raises(FormatError, match=r":2: 2 values"):
        read_imu_to_velo(path)
