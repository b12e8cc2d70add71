"""Defocus synthesis: radius formula, sharp focal plane, disk blur, occlusion, exact replay."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.defocus import (
    DEFOCUS_CAMERAS,
    CameraOptics,
    DefocusParams,
    DefocusRecord,
    blur_kernel,
    blur_radius,
    defocus,
)

# A strong lens so that a few metres give a few pixels of blur: r(inf) = 10 px at D_fp = 5 m.
F, FN, PITCH, FOCUS = 0.05, 2.0, 5e-6, 5.0
R_INF = (F / FN) * F / ((FOCUS - F) * math.sqrt(2) * PITCH)
OPTICS = CameraOptics("test-lens", F, FN, PITCH)


def formula_radius(d, f, fn, p, focus):
    """r(d) = 1 / (sqrt(2) p) * (A f / (D - f)) * |d - D| / d, A = f / F_n, written per pixel."""
    out = np.empty(np.shape(d))
    a = f / fn
    for idx, v in np.ndenumerate(np.asarray(d, dtype=np.float64)):
        if not (math.isfinite(v) and v > 0):
            v = math.inf
        rel = 1.0 if math.isinf(v) else abs(v - focus) / v
        out[idx] = 1 / (math.sqrt(2) * p) * (a * f / (focus - f)) * rel
    return out


def depth_for_radius(r, *, far=True):
    """Depth whose blur radius is r pixels, behind (far) or in front of the focal plane."""
    s = r / R_INF
    return FOCUS / (1 - s) if far else FOCUS / (1 + s)


def disk_kernel_ref(r):
    """Disk of radius r with a one-pixel linear edge, built pixel by pixel."""
    half = int(math.floor(r + 0.5))
    k = np.zeros((2 * half + 1, 2 * half + 1))
    for y in range(-half, half + 1):
        for x in range(-half, half + 1):
            k[y + half, x + half] = min(max(r + 0.5 - math.hypot(x, y), 0.0), 1.0)
    return k / k.sum()


def blur_ref(img, kern):
    """Direct correlation with a symmetric (half-sample) border, as cv2.BORDER_REFLECT."""
    h = kern.shape[0] // 2
    pad = np.pad(img.astype(np.float64), ((h, h), (h, h), (0, 0)), mode="symmetric")
    out = np.zeros(img.shape)
    H, W = img.shape[:2]
    for dy in range(kern.shape[0]):
        for dx in range(kern.shape[1]):
            out += kern[dy, dx] * pad[dy : dy + H, dx : dx + W]
    return out


def texture(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.05, 0.95, (h, w, 3)).astype(np.float32)


def params(**kw):
    return DefocusParams(camera=OPTICS, focus_distance=(FOCUS, FOCUS), **kw)


# ----------------------------------------------------------------- radius


def test_radius_map_equals_formula():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 80.0, (20, 30))
    depth[0, :3] = [0.0, np.nan, np.inf]  # no depth: infinitely far
    ours = blur_radius(depth, focus_distance_m=FOCUS, camera=OPTICS)
    np.testing.assert_allclose(ours, formula_radius(depth, F, FN, PITCH, FOCUS), rtol=1e-12)
    # defocus returns the same map (float32), for every preset too.
    img = texture(20, 30)
    _, radius, rec = defocus(img, depth, params=params(missing="far"))
    np.testing.assert_allclose(radius, formula_radius(depth, F, FN, PITCH, FOCUS), rtol=1e-6)
    assert rec.radius_scale == pytest.approx(R_INF)
    for cam in DEFOCUS_CAMERAS.values():
        r = blur_radius(depth, focus_distance_m=2.0, camera=cam.name)
        ref = formula_radius(depth, cam.focal_length_m, cam.f_number, cam.pixel_pitch_m, 2.0)
        np.testing.assert_allclose(r, ref, rtol=1e-12)


def test_paper_camera_numbers():
    """f = 9 mm, F_n = 2, p = 7.5 um, D_fp = 0.7 m (arXiv 2506.06643): 5.53 px at infinity."""
    cam = DEFOCUS_CAMERAS["dfd-nyu"]
    assert (cam.focal_length_m, cam.f_number, cam.pixel_pitch_m) == (9e-3, 2.0, 7.5e-6)
    r = blur_radius(np.array([[0.7, 1.4, np.inf]]), focus_distance_m=0.7)
    expected_inf = 4.5e-3 * 9e-3 / (0.691 * math.sqrt(2) * 7.5e-6)
    np.testing.assert_allclose(r[0], [0.0, expected_inf / 2, expected_inf], rtol=1e-12)
    assert expected_inf == pytest.approx(5.525, abs=1e-3)


def test_focal_length_from_calibration():
    cam = CameraOptics.from_calibration(721.5377, pixel_pitch_m=4.65e-6, f_number=2.0)
    assert cam.focal_length_m == pytest.approx(721.5377 * 4.65e-6, rel=1e-15)
    assert cam.aperture_m == pytest.approx(cam.focal_length_m / 2.0)
    # With the pitch, r(d) only depends on f_px: r = f_px f / (sqrt(2) F_n (D - f)) |d - D| / d.
    r = blur_radius(np.array([[np.inf]]), focus_distance_m=10.0, camera=cam)[0, 0]
    assert r == pytest.approx(721.5377 * cam.focal_length_m / (math.sqrt(2) * 2 * (10 - 0.003355)))


# ----------------------------------------------------------------- blur


@pytest.mark.parametrize("dtype", [np.uint8, np.float32])
def test_plane_at_focus_distance_stays_identical(dtype):
    img = texture()
    if dtype == np.uint8:
        img = np.rint(img * 255).astype(np.uint8)
    out, radius, _ = defocus(img, np.full(img.shape[:2], FOCUS), params=params())
    assert out.dtype == img.dtype and out.shape == img.shape
    np.testing.assert_array_equal(out, img)
    assert np.all(radius == 0)


@pytest.mark.parametrize("r, far", [(3.0, True), (2.5, False), (6.0, True), (0.75, True)])
def test_plane_at_depth_is_a_disk_blur_of_its_radius(r, far):
    img = texture()
    depth = np.full(img.shape[:2], depth_for_radius(r, far=far))
    out, radius, _ = defocus(img, depth, params=params(layer_step=0.25))
    np.testing.assert_allclose(radius, r, rtol=1e-6)
    np.testing.assert_allclose(blur_kernel(r), disk_kernel_ref(r), atol=1e-7)
    np.testing.assert_allclose(out, blur_ref(img, disk_kernel_ref(r)), atol=2e-5)


def test_gaussian_kernel_option():
    img = texture()
    r = 2.0
    out, _, rec = defocus(img, np.full(img.shape[:2], depth_for_radius(r)),
                          params=params(kernel="gaussian"))  # fmt: skip
    half = math.ceil(3 * r)
    y, x = np.mgrid[-half : half + 1, -half : half + 1]
    k = np.exp(-(x * x + y * y) / (2 * r * r))
    np.testing.assert_allclose(out, blur_ref(img, k / k.sum()), atol=2e-5)
    assert rec.kernel == "gaussian"


def test_radius_is_quantised_to_the_layer_step():
    img = texture()
    r = 2.3  # with a 0.5 px step the layer radius is 2.5
    out, radius, _ = defocus(img, np.full(img.shape[:2], depth_for_radius(r)), params=params())
    np.testing.assert_allclose(radius, r, rtol=1e-6)
    np.testing.assert_allclose(out, blur_ref(img, disk_kernel_ref(2.5)), atol=2e-5)


def test_no_sharp_background_leaks_through_a_blurred_near_edge():
    """A blurred near box over a sharp checkerboard at the focus distance."""
    h, w, r_near = 64, 96, 4.0
    yy, xx = np.mgrid[0:h, 0:w]
    checker = np.where((yy + xx) % 2 == 0, 0.2, 0.8)[:, :, None] * np.ones(3)
    box = np.zeros((h, w), bool)
    box[20:44, 30:66] = True
    colour = np.array([0.9, 0.1, 0.3])
    img = np.where(box[:, :, None], colour, checker).astype(np.float32)
    depth = np.where(box, depth_for_radius(r_near, far=False), FOCUS)
    out, _, _ = defocus(img, depth, params=params())
    # Inside the box: only the box's colour, right up to its edge (no texture through it).
    np.testing.assert_allclose(out[box], np.broadcast_to(colour, out[box].shape), atol=2e-5)
    # Just outside: the box's blurred coverage a over the sharp texture, a = disk blur of the box.
    a = blur_ref(box[:, :, None].astype(np.float64), disk_kernel_ref(r_near))[:, :, 0]
    expected = a[:, :, None] * colour + (1 - a[:, :, None]) * checker
    ring = ~box & (a > 0)
    np.testing.assert_allclose(out[ring], expected[ring], atol=2e-5)
    left_of_edge = out[30, 27:30]  # 1-3 px left of the box
    assert np.all(a[30, 27:30] >= [0.05, 0.2, 0.35])
    assert np.all(np.abs(left_of_edge - checker[30, 27:30]).max(axis=1) > 0.03)
    # Far from the box the texture is untouched.
    np.testing.assert_array_equal(out[a == 0], img[a == 0])


def test_sharp_foreground_stays_sharp_over_a_blurred_background():
    h, w = 40, 60
    img = texture(h, w, seed=3)
    near = np.zeros((h, w), bool)
    near[10:30, 15:40] = True
    depth = np.where(near, FOCUS, depth_for_radius(5.0))  # background blurred by 5 px
    out, _, _ = defocus(img, depth, params=params())
    np.testing.assert_allclose(out[near], img[near], atol=1e-6)
    assert np.abs(out[~near] - img[~near]).mean() > 0.05


def test_missing_depth_is_far_or_refused():
    img = texture(20, 30)
    depth = np.full((20, 30), FOCUS)
    depth[5, 5] = 0.0
    with pytest.raises(ParameterError, match="missing"):
        defocus(img, depth, params=params())
    _, radius, _ = defocus(img, depth, params=params(missing="far"))
    assert radius[5, 5] == pytest.approx(R_INF, rel=1e-6) and radius[0, 0] == 0


def test_grey_image_and_border_pixels():
    img = texture(30, 40)[:, :, 0]
    out, _, _ = defocus(img, np.full(img.shape, depth_for_radius(3.0)), params=params())
    assert out.shape == img.shape
    ref = blur_ref(img[:, :, None], disk_kernel_ref(3.0))[:, :, 0]
    np.testing.assert_allclose(out, ref, atol=2e-5)  # corners use the reflected border too


# ----------------------------------------------------------------- sampling and replay


def test_record_replays_exactly_with_noise():
    img = np.rint(texture(40, 50) * 255).astype(np.uint8)
    rng = np.random.default_rng(4)
    depth = rng.uniform(1.0, 30.0, (40, 50))
    p = DefocusParams(camera=OPTICS, focus_distance=(2.0, 20.0), f_number=(1.4, 4.0),
                      noise="eld", noise_camera="random", ratio=(2, 16))  # fmt: skip
    out, radius, rec = defocus(img, depth, rng=np.random.default_rng(7), params=p)
    text = json.dumps(rec.to_dict())
    again, radius2, rec2 = defocus(img, depth, record=json.loads(text))
    np.testing.assert_array_equal(again, out)
    np.testing.assert_array_equal(radius2, radius)
    assert rec2 == rec and DefocusRecord.from_json(rec.to_json()) == rec
    assert 2.0 <= rec.focus_distance_m <= 20.0 and 1.4 <= rec.f_number <= 4.0
    assert rec.noise.model == "eld" and rec.noise.seed > 0
    np.testing.assert_allclose(
        radius, formula_radius(depth, F, rec.f_number, PITCH, rec.focus_distance_m), rtol=1e-6
    )
    # The same seed gives the same image, another seed another one.
    same, _, _ = defocus(img, depth, rng=7, params=p)
    np.testing.assert_array_equal(same, out)
    other, _, rec3 = defocus(img, depth, rng=8, params=p)
    assert rec3.focus_distance_m != rec.focus_distance_m and not np.array_equal(other, out)
    # Switching the noise off keeps the optics draws (params round-trip through to_dict).
    quiet_params = DefocusParams(**{**p.to_dict(), "noise": "none"})
    assert quiet_params.camera == OPTICS
    _, _, quiet = defocus(img, depth, rng=7, params=quiet_params)
    assert (quiet.focus_distance_m, quiet.f_number) == (rec.focus_distance_m, rec.f_number)


def test_fixed_values_are_recorded_exactly_and_need_no_rng():
    img = texture(10, 12)
    _, _, rec = defocus(img, np.full((10, 12), 3.0), params=params())
    assert DefocusParams(camera=OPTICS, focus_distance=FOCUS).focus_distance == (FOCUS, FOCUS)
    assert rec.focus_distance_m == FOCUS and rec.f_number == FN and rec.noise.model == "none"
    with pytest.raises(ParameterError, match="rng"):
        defocus(img, np.full((10, 12), 3.0), params=params(noise="gaussian"))


def test_noise_brightness_is_unbiased_on_a_flat_patch():
    img = np.full((200, 200, 3), 0.5, np.float32)
    p = params(noise="gaussian", ratio=(4.0, 4.0))
    out, _, rec = defocus(img, np.full((200, 200), FOCUS), rng=0, params=p)
    assert rec.noise.model == "gaussian"
    assert out.mean() == pytest.approx(0.5, abs=0.01) and out.std() > 0.003


# ----------------------------------------------------------------- bad input


def test_bad_input_is_refused():
    img = texture(10, 12)
    with pytest.raises(ParameterError, match=r"--depth: must have shape \(10, 12\)"):
        defocus(img, np.ones((10, 11)), params=params())
    with pytest.raises(ParameterError, match="--focus-distance: .* must be > --focal-length-m"):
        DefocusParams(camera=OPTICS, focus_distance=(0.01, 0.01))
    with pytest.raises(ParameterError, match="--camera: must be one of dfd-nyu"):
        DefocusParams(camera="Hasselblad")
    with pytest.raises(ParameterError, match="--kernel: must be one of disk, gaussian"):
        params(kernel="box")
    with pytest.raises(ParameterError, match="--focus-distance: range is inverted"):
        DefocusParams(focus_distance=(2.0, 1.0))
    with pytest.raises(ParameterError, match=r"--layer-step: must be a finite number in \(0, 4\]"):
        DefocusParams(layer_step=5.0, max_radius=4.0)
    with pytest.raises(ParameterError, match="--f-number: must be a finite number > 0"):
        CameraOptics("x", 0.01, 0.0, 1e-6)
    with pytest.raises(ParameterError, match="0, 1"):
        defocus(img * 2, np.ones((10, 12)), params=params())
    with pytest.raises(ParameterError, match="--image: must be uint8 or float32 or float64"):
        defocus((img * 255).astype(np.uint16), np.ones((10, 12)), params=params())
    with pytest.raises(ParameterError, match="--radius: must be a finite number >= 0"):
        blur_kernel(-1.0)
    _, _, rec = defocus(img, np.ones((10, 12)), params=params())
    with pytest.raises(ParameterError, match="drawn for"):
        defocus(texture(11, 12), np.ones((11, 12)), record=rec)
    bad = rec.to_dict()
    bad["focus_distance_m"] = 0.01
    with pytest.raises(ParameterError, match="--focus-distance-m: .* must be > --focal-length-m"):
        defocus(img, np.ones((10, 12)), record=bad)
    with pytest.raises(ParameterError, match="record"):
        defocus(img, np.ones((10, 12)), record={"height": 10})
