"""Calibration type, intrinsics under resize/crop, and every calibration reader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sparsetools.calibration import Calibration, crop_intrinsics, resize_intrinsics
from sparsetools.errors import CalibrationError, ParameterError
from sparsetools.io.calib import (
    load_calibration,
    read_kitti_object_calib,
    write_json_calib,
    write_kitti_object_calib,
)

K = np.array([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]])


def _calib(**kw):
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    args = dict(K=K, T_cam_from_sensor=T, width=1242, height=375)
    args.update(kw)
    return Calibration(**args)


def _project(P, X):
    x = P @ np.append(X, 1.0)
    return x[:2] / x[2]


def test_resize_maps_pixel_grid_consistently():
    # A point projecting to pixel centre (u, v) must land at s (u + 0.5) - 0.5 after resizing.
    rng = np.random.default_rng(0)
    for s in (0.5, 0.25, 2.0, 0.6441):
        Ks = resize_intrinsics(K, s)
        for _ in range(10):
            X = rng.uniform([-5, -2, 2], [5, 2, 50])
            u = _project(np.hstack([K, np.zeros((3, 1))]), X)
            us = _project(np.hstack([Ks, np.zeros((3, 1))]), X)
            np.testing.assert_allclose(us, s * (u + 0.5) - 0.5, rtol=0, atol=1e-9)


def test_resize_handles_kitti_P_with_translation_column():
    P = np.array([[707.05, 0, 604.08, 45.76], [0, 707.05, 180.51, -0.345], [0, 0, 1, 0.00498]])
    rng = np.random.default_rng(1)
    Ps = resize_intrinsics(P, 0.5)
    for _ in range(10):
        X = rng.uniform([-5, -2, 2], [5, 2, 50])
        np.testing.assert_allclose(_project(Ps, X), 0.5 * (_project(P, X) + 0.5) - 0.5, atol=1e-9)


def test_crop_shifts_principal_point_and_pixels():
    P = np.array([[707.05, 0, 604.08, 45.76], [0, 707.05, 180.51, -0.345], [0, 0, 1, 0.00498]])
    Pc = crop_intrinsics(P, top=100, left=30)
    X = np.array([1.0, 0.5, 12.0])
    np.testing.assert_allclose(_project(Pc, X), _project(P, X) - [30, 100], atol=1e-9)
    Kc = crop_intrinsics(K, top=7, left=3)
    assert Kc[0, 2] == pytest.approx(K[0, 2] - 3) and Kc[1, 2] == pytest.approx(K[1, 2] - 7)


def test_calibration_resized_and_cropped_sizes():
    c = _calib()
    r = c.resized(0.5)
    assert (r.width, r.height) == (621, 188)
    assert r.fx == pytest.approx(c.fx / 2)
    cc = c.cropped(119, 157, 256, 928)  # UltraDepth: 928x256 bottom-centre crop of KITTI
    assert (cc.width, cc.height) == (928, 256)
    assert cc.cx == pytest.approx(c.cx - 157) and cc.cy == pytest.approx(c.cy - 119)
    with pytest.raises(ParameterError, match="does not fit"):
        c.cropped(200, 0, 256, 928)
    with pytest.raises(ParameterError):
        c.cropped(-1, 0, 10, 10)
    with pytest.raises(ParameterError):
        c.resized(0)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(K=np.zeros((3, 3))), "singular"),
        (dict(K=np.eye(2)), "3x3"),
        (dict(T_cam_from_sensor=np.zeros((4, 4))), "singular rotation"),
        (dict(K=np.full((3, 3), np.nan)), "non-finite"),
        (dict(width=0), "positive"),
    ],
)
def test_calibration_rejects_bad_matrices(kw, message):
    with pytest.raises(CalibrationError, match=message):
        _calib(**kw)


def test_size_unknown_is_a_clear_error():
    with pytest.raises(ParameterError, match="image size unknown"):
        _ = _calib(width=None, height=None).size


def test_json_round_trip(tmp_path):
    c = _calib(P=np.hstack([K, [[1.0], [2.0], [0.01]]]))
    write_json_calib(tmp_path / "c.json", c)
    back = load_calibration(tmp_path / "c.json")
    np.testing.assert_array_equal(back.K, c.K)
    np.testing.assert_array_equal(back.T_cam_from_sensor, c.T_cam_from_sensor)
    np.testing.assert_array_equal(back.P, c.P)
    assert (back.width, back.height) == (1242, 375)


def test_kitti_object_writer_reader_round_trip(tmp_path):
    c = _calib()
    write_kitti_object_calib(tmp_path / "000000.txt", c)
    back = read_kitti_object_calib(tmp_path / "000000.txt", image_size=(1242, 375))
    np.testing.assert_allclose(back.projection, c.projection, rtol=1e-11, atol=1e-9)


def test_json_missing_and_bad_keys(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"K": K.tolist()}))
    with pytest.raises(CalibrationError, match="missing key 'T_cam_from_sensor'"):
        load_calibration(p)
    p.write_text(
        json.dumps(
            {"K": [["a", 0, 0], [0, 1, 0], [0, 0, 1]], "T_cam_from_sensor": np.eye(4).tolist()}
        )
    )
    with pytest.raises(CalibrationError, match="non-numeric"):
        load_calibration(p)
    p.write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(p)


KITTI_TXT = """P0: 1 0 0 0 0 1 0 0 0 0 1 0
P2: 7.070493e+02 0 6.040814e+02 4.575831e+01 0 7.070493e+02 1.805066e+02 -3.454157e-01 0 0 1 4.981016e-03
R0_rect: 1 0 0 0 1 0 0 0 1
Tr_velo_to_cam: 0 -1 0 0 0 0 -1 0 1 0 0 0
"""


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.replace("P2:", "P9:"), "missing key 'P2'"),
        (lambda s: s.replace("R0_rect: 1", "R0_rect: x"), "'R0_rect' holds non-numeric"),
        (lambda s: s.replace("Tr_velo_to_cam: 0 -1 0 0", "Tr_velo_to_cam: 0 -1"), "has 10 values"),
        (
            lambda s: s.replace(
                "7.070493e+02 0 6.040814e+02 4.575831e+01 0 7.070493e+02", "0 0 0 0 0 0"
            ),
            "singular",
        ),
    ],
)
def test_kitti_object_bad_files(tmp_path, edit, message):
    p = tmp_path / "000000.txt"
    p.write_text(edit(KITTI_TXT))
    with pytest.raises(CalibrationError, match=message):
        load_calibration(p)


def test_missing_file_and_unknown_format(tmp_path):
    with pytest.raises(CalibrationError, match="no such"):
        load_calibration(tmp_path / "nope.txt")
    (tmp_path / "c.yaml").write_text("a: 1")
    with pytest.raises(Exception, match="unknown calibration format"):
        load_calibration(tmp_path / "c.yaml")
    with pytest.raises(CalibrationError, match="calib_cam_to_cam"):
        load_calibration(tmp_path)


def test_real_kitti_object_and_raw_agree(kitti_object, real_dir):
    obj = load_calibration(kitti_object / "calib" / "000001.txt", image_size=(1242, 375))
    raw = load_calibration(real_dir / "kitti-raw-calib-2011_09_26")
    assert (raw.width, raw.height) == (1242, 375)
    # Same drive date: velo->cam identical; P2 of the object file vs P_rect_02 of the raw file.
    np.testing.assert_allclose(obj.T_cam_from_sensor, raw.T_cam_from_sensor, atol=1e-6)
    np.testing.assert_allclose(obj.P, raw.P, rtol=1e-5)
    # Also reachable through one of the two files.
    raw2 = load_calibration(real_dir / "kitti-raw-calib-2011_09_26" / "calib_velo_to_cam.txt")
    np.testing.assert_array_equal(raw2.P, raw.P)


def test_real_nuscenes_json(nuscenes_demo):
    c = load_calibration(nuscenes_demo / "calib_derived_from_pkl.json", camera="CAM_FRONT")
    assert (c.width, c.height) == (1600, 900)
    assert 1200 < c.fx < 1300
    with pytest.raises(CalibrationError, match="no camera 'CAM_NOPE'"):
        load_calibration(nuscenes_demo / "calib_derived_from_pkl.json", camera="CAM_NOPE")
