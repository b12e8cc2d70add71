"""Low-light synthesis: statistics of brightness and noise, flare placement, exact replay."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import integrate

from sparsetools.errors import ParameterError
from sparsetools.ops.flare import (
    _wave_optics_psf,
    build_flare_bank,
    flare_bank,
    render_flares,
)
from sparsetools.ops.lowlight import LowLightParams, LowLightRecord, lowlight
from sparsetools.ops.noise import (
    CAMERA_PROFILES,
    NoiseParams,
    add_sensor_noise,
    noise_variance,
    sample_noise_params,
)

K = np.array([[200.0, 0.0, 79.5], [0.0, 200.0, 29.5], [0.0, 0.0, 1.0]])


def _day(h=60, w=160, seed=0):
    rng = np.random.default_rng(seed)
    base = np.linspace(30, 220, w)[None, :, None] * np.ones((h, 1, 3))
    return np.clip(base + rng.normal(0, 10, (h, w, 3)), 0, 255).astype(np.uint8)


def _tl_variance(lam: float) -> float:
    """Variance of a unit Tukey-lambda variable from its quantile function (not scipy.stats)."""

    def q2(p):
        q = math.log(p / (1 - p)) if abs(lam) < 1e-9 else (p**lam - (1 - p) ** lam) / lam
        return q * q

    return integrate.quad(q2, 0, 1, limit=200)[0]


# ----------------------------------------------------------------- replay and determinism


@pytest.mark.parametrize("noise", ["eld", "gaussian", "none"])
def test_replay_from_json_record_is_exact(noise):
    img = _day()
    depth = np.where(np.arange(160)[None, :] < 80, 8.0, 40.0) * np.ones((60, 1))
    params = LowLightParams(noise=noise, flare_count=(3, 6), camera="random")
    night, rec = lowlight(img, depth=depth, K=K, rng=np.random.default_rng(5), params=params)
    text = json.dumps(rec.to_dict())  # JSON-serialisable as is
    again, rec2 = lowlight(img, depth=depth, K=K, record=json.loads(text))
    np.testing.assert_array_equal(again, night)
    assert rec2.to_dict() == rec.to_dict()
    # The record alone is enough: no depth, no params, no rng.
    third, _ = lowlight(img, record=LowLightRecord.from_json(rec.to_json()))
    np.testing.assert_array_equal(third, night)
    assert night.dtype == np.uint8 and night.shape == img.shape
    assert len(rec.flares) == rec.flare_count >= 3


def test_same_seed_same_image_other_seed_differs():
    img = _day()
    a, ra = lowlight(img, rng=11)
    b, rb = lowlight(img, rng=np.random.default_rng(11))
    c, rc = lowlight(img, rng=12)
    np.testing.assert_array_equal(a, b)
    assert ra.to_dict() == rb.to_dict()
    assert not np.array_equal(a, c)
    assert rc.noise.seed != ra.noise.seed


def test_record_holds_every_sampled_value():
    _, rec = lowlight(_day(), depth=np.full((60, 160), 5.0), K=K, rng=3)
    d = rec.to_dict()
    for key in ("brightness", "gamma", "flare_count", "flare_scale", "flare_amount", "flares",
                "flare_source", "bank_seed", "bank_count", "bank_size", "noise"):  # fmt: skip
        assert key in d
    for key in (
        "camera",
        "system_gain",
        "sigma_read",
        "sigma_row",
        "tukey_lambda",
        "ratio",
        "seed",
    ):
        assert key in d["noise"]
    f = d["flares"][0]
    for key in ("u", "v", "depth", "point", "side", "pattern", "color", "intensity", "rotation"):
        assert key in f
    p = LowLightParams()
    assert p.brightness[0] <= rec.brightness <= p.brightness[1]
    assert p.gamma[0] <= rec.gamma <= p.gamma[1]
    # N_F = clip(max(floor(F / s_F + 0.5), 1), 1, 20)
    expected = min(max(math.floor(rec.flare_amount / rec.flare_scale + 0.5), 1), 20)
    assert rec.flare_count == expected


def test_switching_noise_off_keeps_other_draws():
    img = _day()
    _, with_noise = lowlight(img, rng=4)
    _, without = lowlight(img, rng=4, params=LowLightParams(noise="none"))
    _, no_flare = lowlight(img, rng=4, params=LowLightParams(flare=False))
    assert with_noise.brightness == without.brightness == no_flare.brightness
    assert with_noise.gamma == without.gamma
    assert [f.to_dict() for f in with_noise.flares] == [f.to_dict() for f in without.flares]
    assert no_flare.noise == with_noise.noise and no_flare.flares == []


# ----------------------------------------------------------------- brightness


def test_brightness_falls_by_s_b_without_noise():
    img = _day()
    params = LowLightParams(flare=False, noise="none")
    for seed in range(6):
        night, rec = lowlight(img, rng=seed, params=params)
        # ((s_b I)^g)^(1/g) = s_b I: exact up to rounding.
        expected = rec.brightness * img.astype(np.float64)
        assert np.max(np.abs(night - expected)) <= 0.5 + 1e-6
        assert night.mean() == pytest.approx(rec.brightness * img.mean(), abs=0.5)


@pytest.mark.parametrize("level", [40, 120, 220])
def test_mean_brightness_with_noise_matches_prediction(level):
    """Mean of a flat patch = E[clip(x + n, 0, 1)^(1/g)], n ~ N(0, predicted variance)."""
    img = np.full((300, 300, 3), level, np.uint8)
    params = LowLightParams(flare=False, noise="gaussian", ratio=(16.0, 16.0))
    night, rec = lowlight(img, rng=level, params=params)
    n = rec.noise
    to_raw = n.saturation / n.ratio
    lin = (rec.brightness * level / 255.0) ** rec.gamma
    var = float(noise_variance(lin * to_raw, n)) / to_raw**2
    # Gauss-Hermite expectation of the output transfer (independent of the simulator).
    xs, ws = np.polynomial.hermite_e.hermegauss(80)
    y = np.clip(lin + math.sqrt(var) * xs, 0, 1) ** (1 / rec.gamma) * 255
    predicted = float(np.sum(ws * y) / np.sum(ws))
    assert night.mean() == pytest.approx(predicted, abs=0.6)
    # And it is darker than the day image by about s_b.
    assert night.mean() == pytest.approx(rec.brightness * level, rel=0.05, abs=1.0)


# ----------------------------------------------------------------- noise statistics


def _noise(model="eld", *, K_gain=2.0, sigma_read=3.0, sigma_row=1.5, lam=0.1, seed=1):
    return NoiseParams(model, "SonyA7S2", K_gain, 1.0, 15871.0, lam, sigma_read, sigma_row, seed)


@pytest.mark.parametrize("model, lam", [("eld", 0.1), ("eld", -0.2), ("gaussian", 0.0)])
def test_noise_variance_linear_in_signal(model, lam):
    """Flat grey patches: variance = K * x + read variance + row variance + 1/12."""
    levels = np.array([0.0, 10.0, 30.0, 100.0, 300.0])
    params = _noise(model, lam=lam, seed=7)
    variances = []
    for i, x in enumerate(levels):
        p = NoiseParams(**{**params.to_dict(), "seed": 100 + i})
        z = add_sensor_noise(np.full((400, 400), x), p)
        variances.append(float(np.var(z - x)))
    # A sample variance has a standard error proportional to itself: weight by 1 / variance.
    slope, intercept = np.polyfit(levels, variances, 1, w=1.0 / np.array(variances))
    read_var = (_tl_variance(lam) if model == "eld" else 1.0) * params.sigma_read**2
    expected_intercept = read_var + params.sigma_row**2 + 1 / 12
    assert slope == pytest.approx(params.system_gain, rel=0.05)
    assert intercept == pytest.approx(expected_intercept, rel=0.06)
    # The closed form used by noise_variance agrees with the quadrature.
    assert float(noise_variance(0.0, params)) == pytest.approx(expected_intercept, rel=1e-6)
    # Mean is unbiased at every level.
    z = add_sensor_noise(np.full((300, 300), 500.0), params)
    assert z.mean() == pytest.approx(500.0, abs=0.5)


def test_end_to_end_variance_of_flat_patches():
    """Through lowlight itself (g = 1, s_b = 1): 8-bit variance = scaled model + rounding."""
    params = LowLightParams(flare=False, brightness=(1, 1), gamma=(1, 1), ratio=(64, 64))
    levels, measured, predicted = [20, 60, 120, 200], [], []
    for level in levels:
        night, rec = lowlight(np.full((300, 400, 3), level, np.uint8), rng=5, params=params)
        n = rec.noise
        dn_per_level = n.saturation / n.ratio / 255.0  # raw DN per 8-bit level
        x = level * dn_per_level
        measured.append(float(night.astype(np.float64).var()))
        predicted.append(float(noise_variance(x, n)) / dn_per_level**2 + 1 / 12)
        assert night.mean() == pytest.approx(level, abs=0.3)
    # The same seed gives the same noise parameters at every level: variance is linear in it.
    np.testing.assert_allclose(measured, predicted, rtol=0.05)
    slope = np.polyfit(levels, measured, 1)[0]
    assert slope == pytest.approx(rec.noise.system_gain / dn_per_level, rel=0.05)


def test_row_noise_is_row_correlated():
    x = np.full((400, 300), 100.0)
    with_rows = add_sensor_noise(x, _noise(sigma_row=4.0, seed=2)) - x
    without = add_sensor_noise(x, _noise(sigma_row=0.0, seed=2)) - x

    def same_row_corr(r):
        return np.corrcoef(r[:, :-1].ravel(), r[:, 1:].ravel())[0, 1]

    def same_col_corr(r):
        return np.corrcoef(r[:-1, :].ravel(), r[1:, :].ravel())[0, 1]

    total = 2.0 * 100 + _tl_variance(0.1) * 9.0 + 16.0 + 1 / 12
    # Neighbours in a row share the row offset: correlation = sigma_row^2 / total variance.
    assert same_row_corr(with_rows) == pytest.approx(16.0 / total, abs=0.03)
    assert abs(same_col_corr(with_rows)) < 0.03
    assert abs(same_row_corr(without)) < 0.03
    # Row means vary by sigma_row (plus the averaged pixel noise).
    assert np.var(with_rows.mean(axis=1)) == pytest.approx(16.0 + (total - 16.0) / 300, rel=0.2)


def test_noise_is_reproducible_from_its_seed_and_channels_share_rows():
    x = np.full((50, 40, 3), 300.0)
    a = add_sensor_noise(x, _noise(seed=9))
    b = add_sensor_noise(x, _noise(seed=9))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, add_sensor_noise(x, _noise(seed=10)))
    # 'none' returns the signal unchanged.
    np.testing.assert_array_equal(add_sensor_noise(x, _noise("none")), x)


def test_sampled_noise_parameters_follow_the_profiles():
    rng = np.random.default_rng(0)
    for name, prof in CAMERA_PROFILES.items():
        draws = [sample_noise_params(rng, camera=name) for _ in range(3000)]
        logk = np.log([d.system_gain for d in draws])
        assert np.all(
            (logk >= math.log(prof.gain_range[0])) & (logk <= math.log(prof.gain_range[1]))
        )
        lam = np.array([d.tukey_lambda for d in draws])
        assert np.all((lam >= prof.lambda_range[0]) & (lam <= prof.lambda_range[1]))
        res_read = np.log([d.sigma_read for d in draws]) - (prof.read_slope * logk + prof.read_bias)
        res_row = np.log([d.sigma_row for d in draws]) - (prof.row_slope * logk + prof.row_bias)
        assert abs(res_read.mean()) < 0.03 and res_read.std() == pytest.approx(
            prof.read_sigma, rel=0.08
        )
        assert abs(res_row.mean()) < 0.03 and res_row.std() == pytest.approx(
            prof.row_sigma, rel=0.08
        )
        # log K uniform: its mean is the middle of the log range.
        assert logk.mean() == pytest.approx(np.log(prof.gain_range).mean(), abs=0.1)


def test_noise_bad_arguments():
    with pytest.raises(ParameterError, match="--camera: must be one of .*SonyA7S2, got 'Leica'"):
        sample_noise_params(np.random.default_rng(0), camera="Leica")
    with pytest.raises(ParameterError, match="--ratio-range: range is inverted"):
        sample_noise_params(np.random.default_rng(0), ratio_range=(4.0, 2.0))
    with pytest.raises(ParameterError, match="--model: must be one of"):
        sample_noise_params(np.random.default_rng(0), model="poisson")
    with pytest.raises(ParameterError, match="--raw: values must be >= 0, got a minimum of -1"):
        add_sensor_noise(np.full((4, 4), -1.0), _noise())
    with pytest.raises(ParameterError, match="--raw: holds NaN"):
        add_sensor_noise(np.full((4, 4), np.nan), _noise())
    with pytest.raises(ParameterError, match=r"--raw: must have shape \(H, W\)"):
        add_sensor_noise(np.zeros(4), _noise())
    with pytest.raises(ParameterError, match="--tukey-lambda: must be a finite number in"):
        add_sensor_noise(np.zeros((4, 4)), NoiseParams(**{**_noise().to_dict(),
                                                          "tukey_lambda": 1.5}))  # fmt: skip
    with pytest.raises(ParameterError):
        add_sensor_noise(np.full((4, 4), 1.0), _noise(K_gain=0.0))


# ----------------------------------------------------------------- flares


def _depth_with_near_region():
    depth = np.full((60, 160), 35.0)  # far: no flare there
    depth[10:30, 100:140] = 12.0  # near region
    depth[40:50, 10:20] = 0.0  # no measurement
    depth[0:5, 0:5] = np.nan
    return depth


def test_flare_sources_only_where_depth_in_range():
    depth = _depth_with_near_region()
    near = np.isfinite(depth) & (depth > 0) & (depth <= 20)
    Kinv = np.linalg.inv(K)
    for seed in range(20):
        _, rec = lowlight(_day(), depth=depth, K=K, rng=seed, params=LowLightParams(noise="none"))
        assert rec.flare_source == "depth"
        for f in rec.flares:
            assert near[f.v, f.u]
            assert f.depth == depth[f.v, f.u]
            expected_point = f.depth * (Kinv @ [f.u, f.v, 1.0])
            np.testing.assert_allclose(f.point, expected_point, rtol=1e-12)
            proj = K @ np.array(f.point)
            assert proj[0] / proj[2] == pytest.approx(f.u) and proj[1] / proj[2] == pytest.approx(
                f.v
            )


def test_added_light_peaks_at_the_recorded_source():
    """Flare image = night(flare on) - night(flare off): its maximum is the light source."""
    img = np.full((60, 160, 3), 30, np.uint8)
    depth = _depth_with_near_region()
    near = np.isfinite(depth) & (depth > 0) & (depth <= 20)
    for seed in range(8):
        on = LowLightParams(noise="none", ghosts=False, flare_count=(1, 1))
        off = LowLightParams(noise="none", ghosts=False, flare=False)
        a, rec = lowlight(img, depth=depth, rng=seed, params=on)
        b, _ = lowlight(img, depth=depth, rng=seed, params=off)
        added = a.astype(int).sum(axis=2) - b.astype(int).sum(axis=2)
        assert added.min() >= 0  # flares only add light
        peak = np.argwhere(added == added.max())
        f = rec.flares[0]
        assert any(abs(r - f.v) <= 1 and abs(c - f.u) <= 1 for r, c in peak)
        assert near[f.v, f.u]


def test_without_depth_sources_are_uniform_and_recorded():
    us, vs = [], []
    for seed in range(40):
        _, rec = lowlight(_day(), rng=seed, params=LowLightParams(noise="none"))
        assert rec.flare_source == "uniform"
        for f in rec.flares:
            assert f.depth is None and f.point is None
            us.append(f.u)
            vs.append(f.v)
    assert min(us) < 30 and max(us) > 130 and min(vs) < 15 and max(vs) > 45


def test_depth_without_eligible_pixel_gives_no_flare():
    night, rec = lowlight(_day(), depth=np.full((60, 160), 50.0), rng=1)
    assert rec.flare_source == "depth-none-in-range" and rec.flares == [] and rec.flare_count == 0
    assert night.shape == (60, 160, 3)


def test_flare_count_range_is_respected():
    for seed in range(10):
        _, rec = lowlight(_day(), rng=seed, params=LowLightParams(flare_count=(4, 4), noise="none"))
        assert rec.flare_count == 4 == len(rec.flares)
        _, rec = lowlight(_day(), rng=seed, params=LowLightParams(flare_count=(1, 2), noise="none"))
        assert 1 <= rec.flare_count <= 2


def test_render_flares_adds_energy_at_image_border():
    bank = flare_bank()
    _, rec = lowlight(_day(), rng=2, params=LowLightParams(noise="none", flare_count=(1, 1)))
    f = rec.flares[0]
    f.u, f.v, f.ghosts = 0, 59, []  # source in the bottom-left corner: clipped sprite
    canvas = render_flares(60, 160, [f], bank=bank, gamma=2.0)
    assert canvas[59, 0].max() == canvas.max() > 0
    assert canvas[:, 100:].max() < canvas.max() * 1e-2


# ----------------------------------------------------------------- flare bank


def test_bank_is_deterministic_and_cached(tmp_path):
    a = build_flare_bank(seed=3, count=3, size=64)
    b = build_flare_bank(seed=3, count=3, size=64)
    np.testing.assert_array_equal(a.patterns, b.patterns)
    np.testing.assert_array_equal(a.ghosts, b.ghosts)
    c = build_flare_bank(seed=4, count=3, size=64)
    assert not np.array_equal(a.patterns, c.patterns)
    # Pattern i depends on (seed, i) only.
    np.testing.assert_array_equal(
        build_flare_bank(seed=3, count=1, size=64).patterns[0], a.patterns[0]
    )
    assert a.patterns.shape == (3, 64, 64, 3) and a.patterns.dtype == np.float32
    assert 0 <= a.patterns.min() and a.patterns.max() <= 1
    # The (saturated) core is centred on (size - 1) / 2 = 31.5, and the edge is dark.
    for p in a.patterns:
        lum = p.sum(axis=2)
        rows, cols = np.nonzero(lum >= 0.99 * lum.max())
        assert abs(rows.mean() - 31.5) <= 1.0 and abs(cols.mean() - 31.5) <= 1.0
        assert lum[0].max() < 0.05 and lum[:, -1].max() < 0.05
    # In memory: the same object; on disk: written once, then loaded with identical arrays.
    from sparsetools.io.flare_bank import _cached, cached_flare_bank

    assert flare_bank(seed=3, count=3, size=64) is flare_bank(seed=3, count=3, size=64)
    m1 = cached_flare_bank(tmp_path, seed=3, count=3, size=64)
    assert cached_flare_bank(tmp_path, seed=3, count=3, size=64) is m1
    files = list(tmp_path.glob("flare-bank-*.npz"))
    assert len(files) == 1
    _cached.cache_clear()
    m2 = cached_flare_bank(tmp_path, seed=3, count=3, size=64)
    assert m2 is not m1
    np.testing.assert_array_equal(m2.patterns, a.patterns)
    assert not m2.patterns.flags.writeable
    # A corrupt cache file is rebuilt, not trusted.
    files[0].write_bytes(b"garbage")
    _cached.cache_clear()
    m3 = cached_flare_bank(tmp_path, seed=3, count=3, size=64)
    np.testing.assert_array_equal(m3.patterns, a.patterns)


def test_wave_optics_psf_is_wider_for_red_than_blue():
    n = 256
    y, x = np.mgrid[0:n, 0:n] - n / 2
    pupil = (x * x + y * y <= 20**2).astype(np.float32)  # clean circular aperture: Airy PSF
    psf = _wave_optics_psf(pupil, n // 2)
    yy, xx = np.mgrid[0 : n // 2, 0 : n // 2] - (n // 2 - 1) / 2
    r2 = xx * xx + yy * yy
    inner = r2 < 15**2
    widths = [float((psf[..., c] * r2)[inner].sum() / psf[..., c][inner].sum()) for c in range(3)]
    assert widths[0] > widths[1] > widths[2]  # diffraction scales with wavelength
    # The PSF of a centred, symmetric pupil is symmetric about its centre.
    np.testing.assert_allclose(psf, psf[::-1, ::-1], atol=1e-3)


# ----------------------------------------------------------------- bad input


def test_bad_images_are_refused_clearly():
    with pytest.raises(ParameterError, match="grey"):
        lowlight(np.zeros((10, 10), np.uint8), rng=0)
    with pytest.raises(ParameterError, match="16-bit"):
        lowlight(np.zeros((10, 10, 3), np.uint16), rng=0)
    with pytest.raises(ParameterError, match="--image: must be uint8"):
        lowlight(np.zeros((10, 10, 3), np.float32), rng=0)
    with pytest.raises(ParameterError, match="--image: is empty"):
        lowlight(np.zeros((0, 10, 3), np.uint8), rng=0)
    with pytest.raises(
        ParameterError, match=r"--depth: must have shape \(60, 160\), got \(30, 80\)"
    ):
        lowlight(_day(), depth=np.ones((30, 80)), rng=0)
    with pytest.raises(ParameterError, match="--K: holds NaN"):
        lowlight(_day(), K=np.full((3, 3), np.nan), rng=0)
    with pytest.raises(ParameterError, match="rng"):
        lowlight(_day())
    with pytest.raises(ParameterError, match="singular"):
        lowlight(_day(), K=np.zeros((3, 3)), rng=0)
    _, rec = lowlight(_day(), rng=0)
    with pytest.raises(ParameterError, match="drawn for"):
        lowlight(_day(h=30), record=rec)
    with pytest.raises(ParameterError, match="record"):
        lowlight(_day(), record={"height": 60})


def test_tampered_records_are_refused():
    img = _day()
    _, rec = lowlight(img, rng=1, params=LowLightParams(flare_count=(2, 2)))
    for change, match in (
        (lambda d: d["flares"][0].update(pattern=99), "not in the bank"),
        (lambda d: d["flares"][0].update(side=10), "odd"),
        (lambda d: d["noise"].update(seed=-5), "seed"),
        (lambda d: d.update(gamma=0.0), "gamma"),
        (lambda d: d.update(version=99), "version"),
    ):
        d = json.loads(rec.to_json())
        change(d)
        with pytest.raises(ParameterError, match=match):
            lowlight(img, record=d)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"brightness": (0.9, 0.5)}, "inverted"),
        ({"gamma": (2.2, 1.8)}, "inverted"),
        ({"ratio": (8.0, 2.0)}, "inverted"),
        ({"flare_scale": (0.0, 1.0)}, "> 0"),
        ({"flare_count": (0, 3)}, ">= 1"),
        ({"flare_count": (5, 2)}, "inverted"),
        ({"noise": "poisson"}, "--noise: must be one of eld, gaussian, none"),
        ({"camera": "Leica"}, "camera"),
        ({"flare_max_depth": -1.0}, "--flare-max-depth: must be a finite number > 0"),
        ({"flare_count": (1.5, 3)}, "--flare-count: must be integers"),
        ({"flare_amount": (0.1, 2e4)}, "--flare-amount: must be <= 10000"),
        ({"brightness": (float("nan"), 1.0)}, "finite"),
    ],
)
def test_bad_params(kwargs, match):
    with pytest.raises(ParameterError, match=match):
        LowLightParams(**kwargs)


# ----------------------------------------------------------------- real KITTI depth


@pytest.mark.real
def test_real_kitti_depth_flares_within_20m(real_dir):
    folder = real_dir / "kitti-depth-gt-metric3d"
    from sparsetools.io.image import read_depth_png, read_image

    img = read_image(folder / "rgb" / "0000000050.png")
    depth = read_depth_png(folder / "depth" / "0000000050.png")
    for seed in range(3):
        night, rec = lowlight(img, depth=depth, rng=seed)
        assert rec.flare_source == "depth"
        assert all(0 < depth[f.v, f.u] <= 20 for f in rec.flares)
        assert night.mean() < img.mean() * 1.02 + 2


# ----------------------------------------------------------------- ELD camera tables


def _package_tables() -> dict:
    """The shipped JSON, read here independently of sparsetools.ops.noise."""
    from importlib.resources import files

    return json.loads((files("sparsetools") / "data" / "eld_cameras.json").read_text("utf-8"))


def _check_profile_against_table(prof, entry):
    fits = entry["Profile-1"]
    assert prof.gain_range == (entry["Kmin"], entry["Kmax"])
    assert (prof.read_slope, prof.read_bias, prof.read_sigma) == tuple(
        fits["G_scale"][k] for k in ("slope", "bias", "sigma")
    )
    assert (prof.gaussian_slope, prof.gaussian_bias, prof.gaussian_sigma) == tuple(
        fits["g_scale"][k] for k in ("slope", "bias", "sigma")
    )
    assert (prof.row_slope, prof.row_bias, prof.row_sigma) == tuple(
        fits["R_scale"][k] for k in ("slope", "bias", "sigma")
    )
    assert prof.tukey_lambdas == tuple(entry["G_shape"])
    assert prof.color_bias == tuple(tuple(r) for r in entry["color_bias"])


def test_profiles_are_the_shipped_tables_with_attribution():
    doc = _package_tables()
    assert "Wei" in doc["attribution"]["paper"] and "MIT" in doc["attribution"]["license"]
    assert "39846c79b5bcb406881c52700d282a9c1149666e" in doc["attribution"]["source_commit"]
    assert sorted(CAMERA_PROFILES) == sorted(doc["cameras"])
    for name, entry in doc["cameras"].items():
        _check_profile_against_table(CAMERA_PROFILES[name], entry)
        assert CAMERA_PROFILES[name].saturation == entry["saturation_dn"]
    # The numbers: SonyA7S2 Gaussian fit 0.5407 / 1.2182 vs Tukey 0.4621 / 0.5657.
    sony = CAMERA_PROFILES["SonyA7S2"]
    assert round(sony.gaussian_slope, 4) == 0.5407 and round(sony.gaussian_bias, 4) == 1.2182
    assert round(sony.read_slope, 4) == 0.4621 and round(sony.read_bias, 4) == 0.5657


@pytest.mark.real
def test_profiles_equal_the_released_eld_tables(real_dir):
    src = json.loads(
        (real_dir / "eld-camera-params" / "eld_camera_params_DERIVED.json").read_text()
    )
    assert sorted(src) == sorted(CAMERA_PROFILES)
    for name, entry in src.items():
        _check_profile_against_table(CAMERA_PROFILES[name], entry)


def test_sampling_uses_the_tables():
    rng = np.random.default_rng(3)
    for name, prof in CAMERA_PROFILES.items():
        eld = [sample_noise_params(rng, camera=name, color_bias=True) for _ in range(2000)]
        rows = np.array([d.table_row for d in eld])
        # lambda is one of the fitted shapes, of the drawn row, rows drawn uniformly
        assert all(d.tukey_lambda == prof.tukey_lambdas[d.table_row] for d in eld)
        counts = np.bincount(rows, minlength=len(prof.tukey_lambdas))
        assert counts.min() > 0.5 * counts.mean() and len(counts) == len(prof.tukey_lambdas)
        # colour bias of the same row: R, mean of the two greens, B
        for d in eld[:50]:
            r, g1, b, g2 = prof.color_bias[d.table_row]
            assert d.color_bias == (r, 0.5 * (g1 + g2), b)
        # Gaussian read noise follows the separate g_scale fit, not the Tukey one.
        gauss = [sample_noise_params(rng, camera=name, model="gaussian") for _ in range(3000)]
        logk = np.log([d.system_gain for d in gauss])
        res = np.log([d.sigma_read for d in gauss]) - (prof.gaussian_slope * logk
                                                        + prof.gaussian_bias)  # fmt: skip
        assert abs(res.mean()) < 0.03
        assert res.std() == pytest.approx(prof.gaussian_sigma, rel=0.08)
        assert all(d.color_bias == (0.0, 0.0, 0.0) for d in gauss)


def test_model_and_color_bias_do_not_change_the_other_draws():
    a = sample_noise_params(np.random.default_rng(9), model="eld")
    b = sample_noise_params(np.random.default_rng(9), model="gaussian", color_bias=True)
    for key in ("system_gain", "ratio", "sigma_row", "seed", "table_row", "tukey_lambda"):
        assert getattr(a, key) == getattr(b, key), key
    assert a.sigma_read != b.sigma_read and any(b.color_bias)


def test_color_bias_shifts_each_channel_mean_only():
    bias = (3.0, -2.0, 0.5)
    x = np.full((300, 300, 3), 200.0)
    plain = _noise(seed=4)
    biased = NoiseParams(**{**plain.to_dict(), "color_bias": bias})
    z0, z1 = add_sensor_noise(x, plain), add_sensor_noise(x, biased)
    np.testing.assert_allclose(z1 - z0, np.broadcast_to(bias, x.shape), atol=1e-9)
    grey = add_sensor_noise(x[:, :, 0], biased) - add_sensor_noise(x[:, :, 0], plain)
    np.testing.assert_allclose(grey, np.mean(bias), atol=1e-9)
    assert float(noise_variance(200.0, biased)) == float(noise_variance(200.0, plain))
    with pytest.raises(ParameterError, match="color_bias"):
        NoiseParams.from_dict({**plain.to_dict(), "color_bias": [1.0, 2.0]})


def test_lowlight_color_bias_option_is_recorded_and_replayed():
    img = _day()
    p = LowLightParams(flare=False, color_bias=True, camera="CanonEOS700D", ratio=(32, 32))
    night, rec = lowlight(img, rng=2, params=p)
    prof = CAMERA_PROFILES["CanonEOS700D"]
    assert rec.noise.color_bias == prof.rgb_bias(rec.noise.table_row)
    again, _ = lowlight(img, record=json.loads(rec.to_json()))
    np.testing.assert_array_equal(again, night)
    without, rec0 = lowlight(img, rng=2, params=LowLightParams(flare=False, camera="CanonEOS700D",
                                                               ratio=(32, 32)))  # fmt: skip
    assert rec0.noise.color_bias == (0.0, 0.0, 0.0) and rec0.noise.seed == rec.noise.seed
    assert not np.array_equal(without, night)  # the same noise, shifted by the offsets
    assert rec.summary()["color_bias"] == list(rec.noise.color_bias)
    with pytest.raises(ParameterError, match="--color-bias: must be True or False"):
        LowLightParams(color_bias="yes")


def test_records_from_before_the_tables_still_replay():
    """A record without color_bias / table_row (layout of the first release) replays as is."""
    img = _day()
    _, rec = lowlight(img, rng=6, params=LowLightParams(noise="eld", flare=False))
    old = rec.to_dict()
    del old["noise"]["color_bias"], old["noise"]["table_row"]
    old["noise"]["tukey_lambda"] = 0.0123  # a uniform draw, not one of the table's shapes
    again, rec2 = lowlight(img, record=old)
    assert rec2.noise.table_row == -1 and rec2.noise.color_bias == (0.0, 0.0, 0.0)
    redo = NoiseParams(**{**rec.noise.to_dict(), "tukey_lambda": 0.0123})
    expected, _ = lowlight(img, record={**rec.to_dict(), "noise": redo.to_dict()})
    np.testing.assert_array_equal(again, expected)


def test_own_camera_tables_file(tmp_path):
    from sparsetools.errors import FormatError
    from sparsetools.io.camera_tables import read_camera_tables

    doc = _package_tables()
    mine = dict(
        doc["cameras"]["SonyA7S2"], Kmin=1.0, Kmax=1.0, G_shape=[0.05], color_bias=[[1, 2, 3, 4]]
    )
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"cameras": {"MyCam": mine}}))
    prof = read_camera_tables(path)["MyCam"]
    assert prof.gain_range == (1.0, 1.0) and prof.tukey_lambdas == (0.05,)
    d = sample_noise_params(np.random.default_rng(0), camera=prof, color_bias=True)
    assert (d.camera, d.system_gain, d.tukey_lambda, d.color_bias) == ("MyCam", 1.0, 0.05,
                                                                       (1.0, 3.0, 3.0))  # fmt: skip
    # The shipped file reads the same as the built-in profiles.
    from importlib.resources import files

    assert read_camera_tables(files("sparsetools") / "data" / "eld_cameras.json") == dict(
        CAMERA_PROFILES
    )
    for text, match in (
        ("{", "cannot read"),
        ('{"cameras": {}}', "non-empty"),
        ('{"cameras": {"X": {"Kmin": 1}}}', "missing"),
        (json.dumps({"cameras": {"X": {**mine, "G_shape": [0.1, 0.2]}}}), "rows"),
        (
            json.dumps({"cameras": {"X": {**mine, "Kmax": float("nan")}}}).replace("NaN", '"x"'),
            "bad value",
        ),
    ):
        path.write_text(text)
        with pytest.raises(FormatError, match=match):
            read_camera_tables(path)
    with pytest.raises(FormatError, match="no such"):
        read_camera_tables(tmp_path / "absent.json")


def test_python_tables_equal_the_shipped_json():
    """ops/ reads no file: its copy of ELD's tables must equal data/eld_cameras.json."""
    from sparsetools.ops.eld_tables import ELD_CAMERAS

    assert ELD_CAMERAS == _package_tables()["cameras"]
