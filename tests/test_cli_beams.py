"""``sparsetools beams``: outputs, resume, multi-N, report, nuScenes, bad input."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from test_beams import cone_scan

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"
KITTI = REAL / "kitti-object-kuixu"
NUSCENES = REAL / "nuscenes-mmdet3d-demo"

CALIB_TXT = """P0: 721.5 0 609.6 0 0 721.5 172.9 0 0 0 1 0
P1: 721.5 0 609.6 -387.6 0 721.5 172.9 0 0 0 1 0
P2: 721.5 0 609.6 44.86 0 721.5 172.9 0.2164 0 0 1 0.002746
P3: 721.5 0 609.6 -339.5 0 721.5 172.9 2.2 0 0 1 0.002729
R0_rect: 1 0 0 0 1 0 0 0 1
Tr_velo_to_cam: 0 -1 0 0 0 0 -1 -0.08 1 0 0 -0.27
Tr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0
"""


def run(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def rows(a: np.ndarray) -> set[bytes]:
    a = np.ascontiguousarray(a, dtype="<f4")
    return {a[i].tobytes() for i in range(a.shape[0])}


@pytest.fixture
def scans(tmp_path):
    """Two synthetic 64-laser scans in scan order + a KITTI-style calib folder."""
    folder = tmp_path / "velodyne"
    calib = tmp_path / "calib"
    folder.mkdir()
    calib.mkdir()
    truth = {}
    for i in range(2):
        pts, ring = cone_scan(np.random.default_rng(i))
        pts.astype("<f4").tofile(folder / f"00000{i}.bin")
        (calib / f"00000{i}.txt").write_text(CALIB_TXT)
        truth[f"00000{i}"] = (pts, ring)
    return folder, calib, truth


def expected_horizon(clouds, n):
    """Rings nearest -0.2, -1.0, ... deg by the far points (r > 20 m) of ``clouds`` pooled.

    The synthetic lasers are not KITTI's, so the shipped profile must not be used for them.
    """
    pts = np.vstack([p for p, _ in clouds]).astype(np.float64)
    ring = np.concatenate([r for _, r in clouds])
    r = np.hypot(pts[:, 0], pts[:, 1])
    el = np.degrees(np.arctan2(pts[:, 2], r))
    medians = {}
    for k in range(64):
        far = (ring == k) & (r > 20)
        sel = far if far.sum() >= 10 else ring == k
        medians[k] = np.median(el[sel])
    chosen = []
    for t in (-0.2 - 0.8 * i for i in range(n)):
        chosen.append(
            min((k for k in medians if k not in chosen), key=lambda k: abs(medians[k] - t))
        )
    return sorted(chosen)


def assert_clean_error(result, code, text):
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    err = result.stderr.strip().splitlines()
    assert any(text in line for line in err), result.stderr
    assert err[-1].startswith("Error") or "Error" in err[-1]


def test_n4_writes_exact_subsets_and_resumes(scans, tmp_path):
    folder, _, truth = scans
    before = {p.name: digest(p) for p in folder.iterdir()}
    out = tmp_path / "out"
    result = run("beams", folder, "--n", 4, "-o", out, "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    rings = expected_horizon(list(truth.values()), 4)
    assert summary["processed"] == 2 and summary["rings_n4"] == ",".join(map(str, rings))
    assert summary["elevations_from"] == "far points of 2 frame(s)"
    assert summary["ring_method"] == "scan-order" and summary["fallback_frames"] == 0
    for stem, (pts, ring) in truth.items():
        got = np.fromfile(out / f"{stem}.bin", "<f4").reshape(-1, 4)
        want = pts[np.isin(ring, rings)]
        assert got.tobytes() == want.tobytes()  # bit-identical rows, input order
    assert {p.name: digest(p) for p in folder.iterdir()} == before
    again = run("beams", folder, "--n", 4, "-o", out, "--json")
    assert again.exit_code == 0
    assert json.loads(again.stdout)["skipped_existing"] == 2


def test_multi_n_with_density(scans, tmp_path):
    folder, calib, truth = scans
    out = tmp_path / "multi"
    result = run(
        "beams",
        folder,
        "--n",
        "1,2,4,16",
        "--calib",
        calib,
        "--image-size",
        "1242x375",
        "-o",
        out,
        "--json",
    )
    assert result.exit_code == 0, result.output
    s = json.loads(result.stdout)
    for n in (1, 2, 4, 16):
        files = sorted((out / f"n{n}").glob("*.bin"))
        assert [f.stem for f in files] == sorted(truth)
        assert s[f"kept_n{n}"] > 0
    assert s["rings_n16"] == ",".join(str(k) for k in range(0, 64, 4))
    assert s["select_n4"] == "horizon" and s["select_n16"] == "uniform"
    dens = [s[f"density_n{n}_pct"] for n in (1, 2, 4, 16)]
    assert dens == sorted(dens) and dens[-1] < s["density_all_pct"]
    assert 0 < s["density_n4_pct"] < 1.0


def test_uniform_rings_and_formats(scans, tmp_path):
    folder, _, truth = scans
    pts, ring = truth["000000"]
    out = tmp_path / "npy"
    result = run(
        "beams",
        folder / "000000.bin",
        "--n",
        8,
        "--select",
        "uniform",
        "--format",
        "npy",
        "-o",
        out,
    )
    assert result.exit_code == 0, result.output
    got = np.load(out / "000000.npy")
    assert got.tobytes() == pts[np.isin(ring, range(0, 64, 8))].tobytes()
    out = tmp_path / "rings"
    result = run("beams", folder / "000000.bin", "--rings", "3,50", "-o", out)
    assert result.exit_code == 0, result.output
    got = np.fromfile(out / "000000.bin", "<f4").reshape(-1, 4)
    assert got.tobytes() == pts[np.isin(ring, [3, 50])].tobytes()


def test_pcd_output_round_trips(scans, tmp_path):
    folder, _, truth = scans
    pts, ring = truth["000001"]
    out = tmp_path / "pcd"
    result = run("beams", folder / "000001.bin", "--n", 2, "--format", "pcd", "-o", out)
    assert result.exit_code == 0, result.output
    from sparsetools.io.pointcloud import read_points

    got = read_points(out / "000001.pcd")
    assert rows(got) == rows(pts[np.isin(ring, expected_horizon([truth["000001"]], 2))])


def test_pl_plus_plus_with_greedy_line_spec(scans, tmp_path):
    folder, calib, _ = scans
    out = tmp_path / "pl"
    result = run(
        "beams",
        folder,
        "--line-spec",
        5,
        7,
        9,
        11,
        "--calib",
        calib,
        "--image-size",
        "1242x375",
        "-o",
        out,
        "--json",
    )
    assert result.exit_code == 0, result.output
    s = json.loads(result.stdout)
    assert s["select_n4"] == "pl++" and s["line_spec_n4"] == "5,7,9,11"
    assert (out / "000000.bin").is_file()


def test_shuffled_cloud_falls_back_with_warning(scans, tmp_path):
    _, _, truth = scans
    pts, ring = truth["000000"]
    perm = np.random.default_rng(0).permutation(pts.shape[0])
    src = tmp_path / "shuffled.bin"
    pts[perm].tofile(src)
    out = tmp_path / "fb"
    result = run("beams", src, "--n", 4, "-o", out, "--json")
    assert result.exit_code == 0, result.output
    assert "recovering rings by elevation" in result.stderr
    s = json.loads(result.stdout)
    assert s["fallback_frames"] == 1 and s["ring_method"] == "elevation"
    got = np.fromfile(out / "shuffled.bin", "<f4").reshape(-1, 4)
    assert rows(got) == rows(pts[np.isin(ring, expected_horizon([truth["000000"]], 4))])


def test_report_prints_the_ring_table(scans):
    folder, _, _ = scans
    result = run("beams", "--report", folder / "000000.bin")
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert "64 rings" in lines[0] and "decreasing" in lines[0]
    assert lines[1].split()[:2] == ["ring", "points"]
    assert len(lines) == 2 + 64
    result = run("beams", "--report", folder / "000000.bin", "--json")
    data = json.loads(result.stdout)
    assert data[0]["rings"] == 64 and len(data[0]["table"]) == 64


# -- bad input -----------------------------------------------------------------------------------


def test_uniform_n_that_does_not_divide(scans, tmp_path):
    folder, _, _ = scans
    out = tmp_path / "bad"
    result = run("beams", folder, "--n", 3, "--select", "uniform", "-o", out)
    assert_clean_error(result, 1, "must divide")
    assert not out.exists() or not any(out.rglob("*.bin"))


def test_pl_plus_plus_needs_calib(scans, tmp_path):
    folder, _, _ = scans
    out = tmp_path / "bad"
    result = run("beams", folder, "--n", 4, "--select", "pl++", "-o", out)
    assert_clean_error(result, 1, "needs --calib")
    assert not out.exists() or not any(out.rglob("*.bin"))


@pytest.mark.parametrize(
    ("content", "text"),
    [
        (b"", "empty file"),
        (np.array([[1, 2, 3, 4], [np.nan, 0, 0, 1]], "<f4").tobytes(), "NaN/Inf"),
        (b"\x00" * 18, "not a multiple"),
    ],
)
def test_bad_files(tmp_path, content, text):
    src = tmp_path / "in" / "000000.bin"
    src.parent.mkdir()
    src.write_bytes(content)
    before = digest(src)
    out = tmp_path / "out"
    result = run("beams", src, "--n", 4, "-o", out)
    assert_clean_error(result, 1, text)
    assert not any(out.rglob("*.bin")) if out.exists() else True
    assert digest(src) == before


def test_cloud_with_fewer_rings_than_asked(scans, tmp_path):
    _, _, truth = scans
    pts, ring = truth["000000"]
    src = tmp_path / "four.bin"
    pts[np.isin(ring, [7, 10, 12, 14])].tofile(src)
    out = tmp_path / "out"
    # Four rings read as a 64-laser scan, no profile: the elevation fallback refuses it.
    result = run("beams", src, "--n", 4, "--profile", "none", "-o", out)
    assert_clean_error(result, 1, "cannot separate 64 lasers")
    # Read as a 4-laser sensor, 8 beams do not exist.
    result = run("beams", src, "--n", 8, "--lasers", 4, "-o", out)
    assert_clean_error(result, 1, "cannot keep 8 beams")
    assert not out.exists() or not any(out.rglob("*.bin"))


def test_usage_errors(scans, tmp_path):
    folder, _, _ = scans
    assert run("beams", folder, "--n", 4).exit_code == 2  # no -o
    assert run("beams", folder, "-o", tmp_path / "x").exit_code == 2  # no N
    assert run("beams", folder, "--n", 0, "-o", tmp_path / "x").exit_code == 2
    assert run("beams", folder, "--n", "1,1", "-o", tmp_path / "x").exit_code == 2
    assert run("beams", folder, "--n", 4, "--pl-grid", "big", "-o", tmp_path / "x").exit_code == 2
    result = run("beams", folder, "--rings", "1,2", "--select", "uniform", "-o", tmp_path / "x")
    assert_clean_error(result, 1, "either --rings or --select")


# -- real data -----------------------------------------------------------------------------------


@pytest.mark.real
def test_real_kitti_frame(tmp_path):
    if not KITTI.is_dir():
        pytest.skip("real data folder ../shared/data/real is absent")
    src = tmp_path / "velodyne"
    src.mkdir()
    shutil.copy(KITTI / "velodyne" / "000001.bin", src)
    out = tmp_path / "out"
    result = run(
        "beams",
        src,
        "--n",
        "4,16",
        "--calib",
        KITTI / "calib",
        "--image",
        KITTI / "image_2",
        "-o",
        out,
        "--json",
    )
    assert result.exit_code == 0, result.output
    s = json.loads(result.stdout)
    assert s["rings_n4"] == "7,10,12,14" and s["elevations_from"] == "profile hdl64e-kitti"
    assert s["density_n4_pct"] < 1.0 < s["density_n16_pct"] < s["density_all_pct"]
    pts = np.fromfile(src / "000001.bin", "<f4").reshape(-1, 4)
    got = np.fromfile(out / "n4" / "000001.bin", "<f4").reshape(-1, 4)
    assert rows(got) <= rows(pts)


@pytest.mark.real
def test_real_nuscenes_uses_the_ring_column(tmp_path):
    files = sorted(NUSCENES.glob("*.pcd.bin")) if NUSCENES.is_dir() else []
    if not files:
        pytest.skip("real data folder ../shared/data/real is absent")
    out = tmp_path / "nu"
    result = run("beams", files[0], "--n", 4, "-o", out, "--json")
    assert result.exit_code == 0, result.output
    s = json.loads(result.stdout)
    assert s["ring_method"] == "column"
    written = list(out.glob("*.pcd.bin"))
    assert len(written) == 1
    got = np.fromfile(written[0], "<f4").reshape(-1, 5)
    assert len(np.unique(got[:, 4])) == 4  # four whole lasers, ring column kept
    assert rows(got) <= rows(np.fromfile(files[0], "<f4").reshape(-1, 5))
