"""Batch job of ``sparsetools beams``: keep 1-32 beams of 64-beam (or 32-beam) scans.

Per frame: read the cloud, recover every point's ring (scan order, validated, with a logged
fall back to elevation; the ring column for nuScenes ``.pcd.bin``), keep the rings of every
requested N and write them, all columns kept, atomically:

- one N (or explicit rings, or a pl++ ``line_spec``): ``OUT/<stem>.bin``;
- several N (``--n 1,2,4,16``): ``OUT/n<N>/<stem>.bin`` for each N.

``.bin`` keeps the input's float32 row layout (nuScenes inputs are written as
``<stem>.pcd.bin``, 5 columns); ``npy`` and ``pcd`` are the other formats.

The rings of ``horizon`` selection are fixed once per batch, before any frame runs (from the
sensor profile, or from the far points of the first frames pooled), so every frame keeps the
same lasers. With a calibration, every frame also reports the density of its projected
sparse depth map per N (valid pixels / all pixels).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError, SparsetoolsError
from ..io.sensor_profile import load_sensor_profile
from ..io.sources import Frame
from ..ops.beams import SELECT_MODES, horizon_rings, pl_line_spec, select_beams, uniform_rings
from ..ops.lidar_profile import SensorProfile
from ..ops.rings import (
    RING_METHODS,
    cone_residual_deg,
    recover_rings_with_method,
    ring_elevations,
    ring_table,
)
from ..validate import check_choice, check_non_negative
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "FORMATS",
    "PROFILE_TOLERANCE_DEG",
    "BeamsInput",
    "BeamsJob",
    "BeamsSettings",
    "beams_tasks",
    "plan_selection",
    "read_cloud_strict",
    "recover_cloud_rings",
    "ring_report",
    "run_beams",
]

log = logging.getLogger(__name__)

FORMATS = ("bin", "npy", "pcd")
#: Frames whose far points are pooled to estimate laser elevations when there is no profile.
_ELEVATION_FRAMES = 5


@dataclass(frozen=True)
class BeamsSettings:
    """Options of a beams run (the same for every frame).

    Attributes
    ----------
    n : tuple of int
        Beam counts to produce (one output set each); empty with ``rings`` / ``line_spec``.
    select : {"horizon", "uniform", "pl++"} or None
        None: horizon for N <= 4, uniform above.
    rings : tuple of int, optional
        Explicit rings (0 = highest).
    ring_method : {"scan-order", "elevation", "column"} or None
        None: ``column`` for nuScenes ``.pcd.bin`` inputs, else ``scan-order``.
    n_lasers : int or None
        None: 32 for nuScenes ``.pcd.bin`` inputs and ``column``, else 64.
    profile : str or None
        ``"auto"`` (the built-in ``hdl64e-kitti`` for 64-laser non-column clouds), ``"none"``,
        a built-in name or a JSON path.
    line_spec : tuple of int, optional
        pl++ elevation bins (implies pl++).
    pl_width, pl_height : int
        pl++ grid.
    fmt : {"bin", "npy", "pcd"}
    far_range : float, metres
    """

    n: tuple[int, ...] = ()
    select: str | None = None
    rings: tuple[int, ...] | None = None
    ring_method: str | None = None
    n_lasers: int | None = field(default=None, metadata={"option": "--lasers"})
    profile: str | None = "auto"
    line_spec: tuple[int, ...] | None = None
    pl_width: int = 1024
    pl_height: int = 64
    fmt: str = field(default="bin", metadata={"option": "--format"})
    far_range: float = 20.0

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)
        if self.select is not None:
            check_choice(self.select, "select", SELECT_MODES)
        if self.ring_method is not None:
            check_choice(self.ring_method, "ring_method", RING_METHODS)
        n = tuple(int(v) for v in self.n)
        object.__setattr__(self, "n", n)
        if any(v < 1 for v in n):
            raise ParameterError(f"N must be >= 1, got {n}")
        if len(set(n)) != len(n):
            raise ParameterError(f"N repeats a value: {n}")
        if self.rings is not None:
            if self.select is not None:
                raise ParameterError("give either --rings or --select, not both")
            if len(n) > 1 or (n and n[0] != len(self.rings)):
                raise ParameterError(f"--n {n} does not match the {len(self.rings)} rings given")
        if self.line_spec is not None:
            if self.select not in (None, "pl++"):
                raise ParameterError("--line-spec belongs to --select pl++")
            if self.rings is not None:
                raise ParameterError("give either --rings or --line-spec, not both")
            if len(n) > 1 or (n and n[0] != len(self.line_spec)):
                raise ParameterError(
                    f"--n {n} does not match the {len(self.line_spec)} bins of --line-spec"
                )
        if not n and self.rings is None and self.line_spec is None:
            raise ParameterError("give the number of beams (--n), --rings or --line-spec")
        if self.n_lasers is not None and not 1 <= self.n_lasers <= 256:
            raise ParameterError(f"--lasers must be in 1..256, got {self.n_lasers}")
        check_non_negative(self.far_range, "far_range")

    @property
    def mode(self) -> str:
        """``rings``, ``pl++``, or the ``select`` asked ("" = the default for each N)."""
        if self.rings is not None:
            return "rings"
        if self.line_spec is not None or self.select == "pl++":
            return "pl++"
        return self.select or ""

    @property
    def multi(self) -> bool:
        return len(self.n) > 1


# -- reading and rings ---------------------------------------------------------------------------


def _is_nuscenes(path: str | os.PathLike) -> bool:
    return Path(path).name.lower().endswith(".pcd.bin")


def read_cloud_strict(path: str | os.PathLike) -> np.ndarray:
    """Read a cloud for beam selection: empty files and NaN/Inf values are errors.

    (The general reader drops non-finite rows with a warning; here every row must be kept or
    refused, since outputs are exact subsets of the input.)

    Returns
    -------
    (N, C) float32, rows in file order
    """
    from ..io.pointcloud import cloud_kind, read_points

    p = Path(path)
    kind = cloud_kind(p)
    if kind in ("kitti-bin", "nuscenes-bin"):
        columns = 4 if kind == "kitti-bin" else 5
        try:
            data = p.read_bytes()
        except FileNotFoundError as exc:
            raise FormatError(f"{p}: no such file") from exc
        except IsADirectoryError as exc:
            raise FormatError(f"{p}: is a folder, expected a point cloud") from exc
        except OSError as exc:
            raise FormatError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        if len(data) % (4 * columns):
            raise FormatError(
                f"{p}: size {len(data)} bytes is not a multiple of {4 * columns} "
                f"({columns} float32 per point): truncated or not a point cloud"
            )
        raw = np.frombuffer(data, dtype="<f4")
        points = raw.reshape(-1, columns).astype(np.float32)
    elif kind == "npy":
        from ..io.npy import load_npy

        try:
            data = p.read_bytes()
        except FileNotFoundError as exc:
            raise FormatError(f"{p}: no such file") from exc
        except OSError as exc:
            raise FormatError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        points = load_npy(data, source=str(p))
        if points.ndim != 2 or points.shape[1] < 3 or points.dtype.kind not in "fiu":
            raise FormatError(
                f"{p}: expected a numeric (N, C>=3) array, got {points.dtype} {points.shape}"
            )
        with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: Inf, refused below
            points = points.astype(np.float32)
    else:  # PCD / PLY through Open3D
        points = read_points(p)
    if points.shape[0] == 0:
        raise FormatError(f"{p}: empty file (no points)")
    bad = int(np.count_nonzero(~np.isfinite(points).all(axis=1)))
    if bad:
        raise FormatError(f"{p}: {bad} point(s) hold NaN/Inf values (corrupt file?)")
    return points


def _resolved(settings: BeamsSettings, path: str | os.PathLike) -> tuple[str, int]:
    method = settings.ring_method or ("column" if _is_nuscenes(path) else "scan-order")
    n_lasers = settings.n_lasers or (32 if method == "column" or _is_nuscenes(path) else 64)
    return method, n_lasers


#: A default profile is used only on clouds whose points lie this close (deg, median) to its
#: cones; KITTI scans fit the shipped HDL-64E profile to ~0.001 deg.
PROFILE_TOLERANCE_DEG = 0.05


def _profile_for(
    settings: BeamsSettings, method: str, n_lasers: int
) -> tuple[SensorProfile | None, bool]:
    """(profile, chosen by the user). ``auto`` picks hdl64e-kitti for 64-laser clouds."""
    name = settings.profile
    if name is None or name == "none":
        return None, False
    explicit = name != "auto"
    if not explicit:
        if method == "column" or n_lasers != 64:
            return None, False
        name = "hdl64e-kitti"
    profile = load_sensor_profile(name)
    if profile.n_lasers != n_lasers:
        raise ParameterError(
            f"sensor profile {profile.name!r} has {profile.n_lasers} lasers, the clouds {n_lasers}"
        )
    return profile, explicit


def recover_cloud_rings(
    points: np.ndarray, path: str | os.PathLike, settings: BeamsSettings
) -> tuple[np.ndarray, str, int]:
    """Rings of one cloud as the settings ask: (ring, method used, n_lasers)."""
    method, n_lasers = _resolved(settings, path)
    profile, explicit = _profile_for(settings, method, n_lasers)
    try:
        ring, used = recover_rings_with_method(
            points,
            n_lasers=n_lasers,
            method=method,
            profile=profile,
            profile_tolerance_deg=None if explicit else PROFILE_TOLERANCE_DEG,
        )
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from exc
    return ring, used, n_lasers


# -- the plan: which rings every N keeps ---------------------------------------------------------


@dataclass(frozen=True)
class _Plan:
    """Per output set: (label, N, rings or None for pl++, line_spec or None); modes."""

    items: tuple[tuple[str, int, tuple[int, ...] | None, tuple[int, ...] | None], ...]
    elevation_source: str = ""
    modes: tuple[str, ...] = ()


def plan_selection(clouds: list[Path], settings: BeamsSettings) -> _Plan:
    """Fix the rings (or pl++ bins) of every output set before the batch runs.

    ``horizon`` uses the profile's elevations, else the far points of the first readable
    frames pooled (so every frame keeps the same lasers). Raises for an N that does not fit
    the selection, before anything is written.
    """
    method, n_lasers = _resolved(settings, clouds[0])
    if settings.rings is not None:
        rings = tuple(sorted(int(k) for k in settings.rings))
        if len(set(rings)) != len(rings) or rings[0] < 0 or rings[-1] >= n_lasers:
            raise ParameterError(
                f"--rings must be distinct values in 0..{n_lasers - 1}, got {settings.rings}"
            )
        return _Plan((("", len(rings), rings, None),), modes=("rings",))
    if settings.mode == "pl++":
        if settings.line_spec is not None:
            spec = tuple(settings.line_spec)
            bad = [b for b in spec if not 0 <= b < settings.pl_height]
            if bad or len(set(spec)) != len(spec):
                raise ParameterError(
                    f"--line-spec bins must be distinct values in 0..{settings.pl_height - 1}, "
                    f"got {spec}"
                )
            return _Plan((("", len(spec), None, spec),), modes=("pl++",))
        items = []
        for n in settings.n:
            spec = pl_line_spec(n, height=settings.pl_height)
            items.append((f"n{n}" if settings.multi else "", n, None, spec))
        return _Plan(tuple(items), modes=("pl++",) * len(items))
    items, modes = [], []
    elevations = None
    source = ""
    for n in settings.n:
        if n > n_lasers:
            raise ParameterError(f"the sensor has {n_lasers} lasers, cannot keep {n} beams")
        mode = settings.select or ("horizon" if n <= 4 else "uniform")
        if mode == "uniform":
            rings = uniform_rings(n_lasers, n)
        else:
            if elevations is None:
                elevations, source = _laser_elevations(clouds, settings, method, n_lasers)
            rings = horizon_rings(elevations, n)
        items.append((f"n{n}" if settings.multi else "", n, rings, None))
        modes.append(mode)
    return _Plan(tuple(items), source, tuple(modes))


def _laser_elevations(clouds, settings, method, n_lasers) -> tuple[np.ndarray, str]:
    profile, explicit = _profile_for(settings, method, n_lasers)
    if profile is not None and explicit:
        return profile.elevation_deg, f"profile {profile.name}"
    pooled_points, pooled_rings, used = [], [], []
    first_error = None
    for path in clouds:
        if len(used) == _ELEVATION_FRAMES:
            break
        try:
            points = read_cloud_strict(path)
            ring, _, _ = recover_cloud_rings(points, path, settings)
        except SparsetoolsError as exc:  # that frame fails again in its own job
            log.info("%s: not used for the laser elevations (%s)", path, exc)
            first_error = first_error or exc
            continue
        pooled_points.append(points[:, :3])
        pooled_rings.append(ring)
        used.append(path)
    if not used:
        raise FormatError(f"no cloud can be read to measure the laser elevations: {first_error}")
    if profile is not None:  # the default profile, if it fits these clouds
        misfit = cone_residual_deg(pooled_points[0], profile, pooled_rings[0])
        if misfit <= PROFILE_TOLERANCE_DEG:
            return profile.elevation_deg, f"profile {profile.name}"
        log.info(
            "sensor profile %s does not fit %s (median %.3f deg off its cones): laser "
            "elevations from far points instead",
            profile.name,
            used[0],
            misfit,
        )
    el = ring_elevations(
        np.vstack(pooled_points),
        np.concatenate(pooled_rings),
        n_lasers=n_lasers,
        far_range=settings.far_range,
    )
    return el, f"far points of {len(used)} frame(s)"


# -- the per-frame job ---------------------------------------------------------------------------


def _output_suffix(settings: BeamsSettings, cloud: Path) -> str:
    if settings.fmt == "bin":
        return ".pcd.bin" if _is_nuscenes(cloud) else ".bin"
    return f".{settings.fmt}"


def _frame_calibration(calib_path, image, image_size, camera=2):
    from ..io.calib import load_calibration
    from ..io.image import check_pixel_count, image_size_of

    calib = load_calibration(calib_path, camera=camera)
    if image_size is not None:
        calib = calib.for_size(*image_size, given_by="--image-size")
    elif image is not None:
        calib = calib.for_size(*image_size_of(image), given_by=f"image {image}")
    elif calib.width is None or calib.height is None:
        raise ParameterError(
            f"image size missing: give --image-size WxH or --image IMG "
            f"(calibration {calib.source or calib_path} holds none)"
        )
    check_pixel_count(calib.width, calib.height, "depth map")
    return calib


def _density_pct(points: np.ndarray, calib) -> tuple[float, int]:
    from ..ops.projection import project_points

    depth = project_points(points, calib)
    valid = int(np.count_nonzero(depth))
    return 100.0 * valid / depth.size, valid


@dataclass(frozen=True)
class BeamsInput:
    """One frame's inputs: its cloud and (for density and pl++) calibration and image."""

    cloud: str
    calib_path: str | None = None
    image: str | None = None


@dataclass(frozen=True)
class BeamsJob:
    """The per-frame job of ``beams`` (picklable): recover rings, keep every output set's
    beams and write them (atomically).

    Returns per frame: points_in, ring_method (``elevation`` after a fall back), rings_found,
    kept_<label> per output set and, with a calibration, density_<label>_pct and
    density_all_pct (the full cloud).
    """

    settings: BeamsSettings
    plan: _Plan
    image_size: tuple[int, int] | None = None

    def __call__(self, task: FrameTask[BeamsInput]) -> dict:
        from ..io.pointcloud import write_points

        settings, plan, inp = self.settings, self.plan, task.inputs
        cloud = Path(inp.cloud)
        points = read_cloud_strict(cloud)
        needs_rings = any(rings is not None for _, _, rings, _ in plan.items)
        calib = None
        if inp.calib_path is not None:
            calib = _frame_calibration(inp.calib_path, inp.image, self.image_size)
        stats: dict = {"points_in": int(points.shape[0])}
        ring = None
        n_lasers = _resolved(settings, cloud)[1]
        if needs_rings:
            ring, used, n_lasers = recover_cloud_rings(points, cloud, settings)
            stats["ring_method"] = used
            stats["ring_fallback"] = int(used != _resolved(settings, cloud)[0])
            stats["rings_found"] = int(np.unique(ring).size)
        selections = []
        for label, n, rings, spec in plan.items:  # select everything first: errors write nothing
            if rings is not None:
                sel = select_beams(points, ring, rings=rings, n_lasers=n_lasers)
            else:
                if calib is None:
                    raise ParameterError("pl++ needs --calib (its image-FOV pre-filter)")
                sel = select_beams(
                    points,
                    line_spec=spec,
                    calib=calib,
                    pl_width=settings.pl_width,
                    pl_height=settings.pl_height,
                )
            selections.append((label or f"n{n}", sel))
        for (key, sel), out in zip(selections, task.outputs.values(), strict=True):
            write_points(out, sel.points)
            stats[f"kept_{key}"] = int(sel.index.size)
            if calib is not None:
                stats[f"density_{key}_pct"], _ = _density_pct(sel.points, calib)
        if calib is not None:
            stats["density_all_pct"], _ = _density_pct(points, calib)
        return stats


# -- tasks and running ---------------------------------------------------------------------------


def beams_tasks(
    frames: list[Frame], out_dir: str | os.PathLike, settings: BeamsSettings, plan: _Plan
) -> list[FrameTask[BeamsInput]]:
    """One task per frame: ``OUT/<sequence>/<frame><suffix>``, or ``OUT/n<N>/<sequence>/...``
    per beam count when several are asked."""
    out = Path(out_dir)
    tasks = []
    for f in frames:
        suffix = _output_suffix(settings, f.cloud)
        outputs = {
            (label or "cloud"): f.key.path(out, suffix, prefix=label)
            for label, _, _, _ in plan.items
        }
        inp = BeamsInput(
            cloud=str(f.cloud),
            calib_path=None if f.calib is None else str(f.calib),
            image=None if f.image is None else str(f.image),
        )
        sources = (
            f.cloud,
            *([f.calib] if f.calib else []),
            *([f.image] if f.image and f.calib else []),
        )
        tasks.append(FrameTask(f.key, inp, outputs, sources))
    return tasks


def _plan_record(plan: _Plan) -> dict:
    """The selection of every output set, compared on a rerun like a setting."""
    out = {}
    for (label, n, rings, spec), mode in zip(plan.items, plan.modes, strict=True):
        key = f"selected {label or f'n{n}'}"
        out[key] = (
            f"{mode} rings {','.join(map(str, rings))}"
            if rings is not None
            else (f"pl++ line spec {','.join(map(str, spec))}")
        )
    return out


def run_beams(
    frames: list[Frame],
    out_dir: str | os.PathLike,
    settings: BeamsSettings,
    *,
    image_size: tuple[int, int] | None = None,
    batch: Batch | None = None,
    inputs: list[str | os.PathLike] = (),
) -> RunSummary:
    """Run ``beams`` over frames (from :func:`sparsetools.io.sources.cloud_frames`).

    Parameters
    ----------
    frames : list of Frame
        Clouds, with a calibration (file, KITTI raw folder or per frame) and image for the
        density report and pl++.
    out_dir : path-like
    settings : BeamsSettings
    image_size : (width, height), optional
        Map size when the calibration holds none.
    batch : Batch, optional
    inputs : list of path-like
        The folders the user gave (the output may not be inside them).

    Returns
    -------
    RunSummary
        Totals: select_<label>, rings_<label> / line_spec_<label> per output set,
        elevations_from, ring_method, fallback_frames, points_in, kept_<label>,
        kept_<label>_pct and, with a calibration, density_<label>_pct (mean over frames) and
        density_all_pct, format, output.
    """
    batch = batch or Batch()
    if not frames:
        raise ParameterError("no point clouds given")
    has_calib = any(f.calib is not None for f in frames)
    if settings.mode == "pl++" and not has_calib:
        raise ParameterError("--select pl++ needs --calib (its image-FOV pre-filter)")
    if has_calib:
        f0 = frames[0]
        try:
            _frame_calibration(f0.calib, f0.image, image_size)
        except ParameterError:
            raise
        except SparsetoolsError:  # that frame's own problem: reported by its job
            pass
    plan = plan_selection([f.cloud for f in frames], settings)
    out = check_output_dir(out_dir, inputs)
    tasks = beams_tasks(frames, out, settings, plan)
    from .provenance import option_names

    selected = _plan_record(plan)
    spec = RunSpec(
        "beams",
        out,
        {**_settings_with(settings, image_size), **selected},
        noun="beams",
        options={**option_names(settings), **{k: k for k in selected}},
    )
    summary = run_frames(BeamsJob(settings, plan, image_size), tasks, batch=batch, spec=spec)
    return _with_totals(summary, settings, plan, out)


def _settings_with(settings: BeamsSettings, image_size) -> dict:
    from .provenance import settings_dict

    d = settings_dict(settings)
    d["image_size"] = list(image_size) if image_size else None
    return d


def _with_totals(
    summary: RunSummary, settings: BeamsSettings, plan: _Plan, out: Path
) -> RunSummary:
    done = summary.ok
    result: dict = {}
    if plan.elevation_source:
        result["elevations_from"] = plan.elevation_source
    points_in = summary.total("points_in")
    result["points_in"] = int(points_in)
    if any("ring_method" in r.stats for r in done):
        methods = sorted({r.stats["ring_method"] for r in done if "ring_method" in r.stats})
        result["ring_method"] = ",".join(methods)
        result["fallback_frames"] = int(summary.total("ring_fallback"))
    for (label, n, rings, spec), mode in zip(plan.items, plan.modes, strict=True):
        key = label or f"n{n}"
        result[f"select_{key}"] = mode
        if rings is not None:
            result[f"rings_{key}"] = ",".join(str(k) for k in rings)
        else:
            result[f"line_spec_{key}"] = ",".join(str(k) for k in spec)
        kept = summary.total(f"kept_{key}")
        result[f"kept_{key}"] = int(kept)
        result[f"kept_{key}_pct"] = round(100.0 * kept / points_in, 3) if points_in else 0.0
        dens = [r.stats[f"density_{key}_pct"] for r in done if f"density_{key}_pct" in r.stats]
        if dens:
            result[f"density_{key}_pct"] = round(float(np.mean(dens)), 4)
    dens_all = [r.stats["density_all_pct"] for r in done if "density_all_pct" in r.stats]
    if dens_all:
        result["density_all_pct"] = round(float(np.mean(dens_all)), 4)
    result["format"] = settings.fmt
    result["output"] = str(out)
    return summary.with_totals(result)


def ring_report(clouds: list[str | os.PathLike], settings: BeamsSettings) -> list[dict]:
    """Ring table of each cloud (files or folders): method used, rings, per-ring statistics."""
    from ..io.sources import cloud_frames

    out = []
    for f in cloud_frames(list(clouds)):
        path = f.cloud
        points = read_cloud_strict(path)
        ring, used, n_lasers = recover_cloud_rings(points, path, settings)
        table = ring_table(points, ring, far_range=settings.far_range)
        out.append(
            {
                "cloud": str(path),
                "points": int(points.shape[0]),
                "n_lasers": n_lasers,
                "ring_method": used,
                **table.as_dict(),
                "_table": table,
            }
        )
    return out
