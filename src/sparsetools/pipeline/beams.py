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
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError, ParameterError, SparsetoolsError
from ..io.pointcloud import read_points
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
from ..validate import check_choice, check_int_range, check_non_negative, parse_size
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask
from .provenance import option_names, settings_dict

__all__ = [
    "FORMATS",
    "PROFILE_TOLERANCE_DEG",
    "BeamsInput",
    "BeamsJob",
    "BeamsSettings",
    "BeamsStats",
    "plan_selection",
    "recover_cloud_rings",
    "ring_report",
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
    image_size : (width, height), optional
        Size of the density maps when the calibration holds none.
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
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        check_choice(self.fmt, "--format", FORMATS)
        if self.select is not None:
            check_choice(self.select, "select", SELECT_MODES)
        if self.ring_method is not None:
            check_choice(self.ring_method, "ring_method", RING_METHODS)
        n = tuple(check_int_range(v, "--n", low=1) for v in self.n)
        object.__setattr__(self, "n", n)
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
        if self.n_lasers is not None:
            check_int_range(self.n_lasers, "--lasers", low=1, high=256)
        check_non_negative(self.far_range, "far_range")
        if self.image_size is not None:
            object.__setattr__(self, "image_size", parse_size(self.image_size))

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
        rings = tuple(sorted(check_int_range(k, "rings", low=0, high=n_lasers - 1)
                             for k in settings.rings))  # fmt: skip
        if len(set(rings)) != len(rings):
            raise ParameterError(f"a ring is given twice: {settings.rings}", param="rings")
        return _Plan((("", len(rings), rings, None),), modes=("rings",))
    if settings.mode == "pl++":
        if settings.line_spec is not None:
            spec = tuple(check_int_range(b, "line_spec", low=0, high=settings.pl_height - 1)
                         for b in settings.line_spec)  # fmt: skip
            if len(set(spec)) != len(spec):
                raise ParameterError(f"a bin is given twice: {spec}", param="line_spec")
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
            points = read_points(path, strict=True)
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


def _frame_calibration(inp: BeamsInput, image_size):
    from ..io.calib import check_sensor, frame_calibration

    calib = frame_calibration(calib_path=inp.calib_path, image=inp.image, image_size=image_size)
    check_sensor(calib, inp.cloud)
    return calib


def _density_pct(points: np.ndarray, calib) -> float:
    from ..ops.projection import project_points

    depth = project_points(points, calib)
    return 100.0 * int(np.count_nonzero(depth)) / depth.size


@dataclass(frozen=True)
class BeamsInput:
    """One frame's inputs: its cloud and (for density and pl++) calibration and image."""

    cloud: str
    calib_path: str | None = None
    image: str | None = None


@dataclass(frozen=True)
class BeamsStats(FrameStats):
    """One frame: points read; with rings, the ring method used (``elevation`` after a fall
    back), whether it fell back, rings found; per output set (``n4``, or ``n<N>`` of a single
    set) the points kept and, with a calibration, the density of its projected map (percent of
    the pixels); and the density of the full cloud's map.

    Recorded flat, as ``kept_<set>`` and ``density_<set>_pct``.
    """

    points_in: int
    kept: Mapping[str, int] = field(default_factory=dict)
    density_pct: Mapping[str, float] = field(default_factory=dict)
    ring_method: str | None = None
    ring_fallback: int | None = None
    rings_found: int | None = None
    density_all_pct: float | None = None

    def to_record(self) -> dict:
        out: dict = {"points_in": self.points_in}
        for name in ("ring_method", "ring_fallback", "rings_found"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        for key, kept in self.kept.items():
            out[f"kept_{key}"] = kept
            if key in self.density_pct:
                out[f"density_{key}_pct"] = self.density_pct[key]
        if self.density_all_pct is not None:
            out["density_all_pct"] = self.density_all_pct
        return out

    @classmethod
    def from_record(cls, record: Mapping) -> BeamsStats:
        kept = {k[len("kept_") :]: v for k, v in record.items() if k.startswith("kept_")}
        density = {k[len("density_"):-len("_pct")]: v for k, v in record.items()
                   if k.startswith("density_") and k.endswith("_pct") and k != "density_all_pct"}  # fmt: skip
        return cls(
            points_in=int(record.get("points_in", 0)),
            kept=kept,
            density_pct=density,
            ring_method=record.get("ring_method"),
            ring_fallback=record.get("ring_fallback"),
            rings_found=record.get("rings_found"),
            density_all_pct=record.get("density_all_pct"),
        )


@dataclass(frozen=True)
class BeamsJob(BatchJob[BeamsInput]):
    """``sparsetools beams`` (picklable): per frame, recover rings, keep every output set's
    beams and write them (atomically).

    Attributes
    ----------
    settings : BeamsSettings
    plan : the rings (or pl++ bins) of every output set, fixed by :meth:`planned` before any
        frame runs, so every frame keeps the same lasers.
    """

    command: ClassVar[str] = "beams"
    noun: ClassVar[str] = "beams"
    stats_type: ClassVar[type[FrameStats]] = BeamsStats

    settings: BeamsSettings
    plan: _Plan | None = None

    def planned(self, frames: list[Frame]) -> BeamsJob:
        """Fix every output set's rings; check pl++'s calibration and the first frame's
        calibration (no size, a size that contradicts it) before anything is written."""
        if not frames:
            raise ParameterError("no point clouds given")
        has_calib = any(f.calib is not None for f in frames)
        if self.settings.mode == "pl++" and not has_calib:
            raise ParameterError("--select pl++ needs --calib (its image-FOV pre-filter)")
        if has_calib:
            f0 = frames[0]
            try:
                _frame_calibration(self._input(f0), self.settings.image_size)
            except ParameterError:
                raise
            except SparsetoolsError:  # that frame's own problem: reported by its job
                pass
        return replace(self, plan=plan_selection([f.cloud for f in frames], self.settings))

    @staticmethod
    def _input(f: Frame) -> BeamsInput:
        return BeamsInput(
            cloud=str(f.cloud),
            calib_path=None if f.calib is None else str(f.calib),
            image=None if f.image is None else str(f.image),
        )

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[BeamsInput]]:
        """One task per frame: ``OUT/<sequence>/<frame><suffix>``, or
        ``OUT/n<N>/<sequence>/...`` per beam count when several are asked."""
        tasks = []
        for f in frames:
            suffix = _output_suffix(self.settings, f.cloud)
            outputs = {
                (label or "cloud"): f.key.path(out_dir, suffix, prefix=label)
                for label, _, _, _ in self.plan.items
            }
            sources = (
                f.cloud,
                *([f.calib] if f.calib else []),
                *([f.image] if f.image and f.calib else []),
            )
            tasks.append(FrameTask(f.key, self._input(f), outputs, sources))
        return tasks

    def record(self) -> dict:
        """The settings and the selection of every output set (compared like a setting)."""
        return {**settings_dict(self.settings), **_plan_record(self.plan)}

    def option_names(self) -> dict:
        return {**option_names(self.settings), **{k: k for k in _plan_record(self.plan)}}

    def __call__(self, task: FrameTask[BeamsInput]) -> BeamsStats:
        from ..io.pointcloud import write_points

        settings, plan, inp = self.settings, self.plan, task.inputs
        cloud = Path(inp.cloud)
        points = read_points(cloud, strict=True)
        needs_rings = any(rings is not None for _, _, rings, _ in plan.items)
        calib = None
        if inp.calib_path is not None:
            calib = _frame_calibration(inp, settings.image_size)
        ring = used = None
        n_lasers = _resolved(settings, cloud)[1]
        if needs_rings:
            ring, used, n_lasers = recover_cloud_rings(points, cloud, settings)
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
        kept, density = {}, {}
        for (key, sel), out in zip(selections, task.outputs.values(), strict=True):
            write_points(out, sel.points)
            kept[key] = int(sel.index.size)
            if calib is not None:
                density[key] = _density_pct(sel.points, calib)
        return BeamsStats(
            points_in=int(points.shape[0]),
            kept=kept,
            density_pct=density,
            ring_method=used,
            ring_fallback=None if used is None else int(used != _resolved(settings, cloud)[0]),
            rings_found=None if ring is None else int(np.unique(ring).size),
            density_all_pct=None if calib is None else _density_pct(points, calib),
        )

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Totals: select_<set>, rings_<set> / line_spec_<set>, elevations_from, ring_method,
        fallback_frames, points_in, kept_<set>, kept_<set>_pct and, with a calibration,
        density_<set>_pct (mean over frames) and density_all_pct; format, output."""
        settings, plan = self.settings, self.plan
        stats = self.stats(summary)
        result: dict = {}
        if plan.elevation_source:
            result["elevations_from"] = plan.elevation_source
        points_in = sum(st.points_in for st in stats)
        result["points_in"] = int(points_in)
        methods = sorted({st.ring_method for st in stats if st.ring_method is not None})
        if methods:
            result["ring_method"] = ",".join(methods)
            result["fallback_frames"] = int(sum(st.ring_fallback or 0 for st in stats))
        for (label, n, rings, spec), mode in zip(plan.items, plan.modes, strict=True):
            key = label or f"n{n}"
            result[f"select_{key}"] = mode
            if rings is not None:
                result[f"rings_{key}"] = ",".join(str(k) for k in rings)
            else:
                result[f"line_spec_{key}"] = ",".join(str(k) for k in spec)
            kept = sum(st.kept.get(key, 0) for st in stats)
            result[f"kept_{key}"] = int(kept)
            result[f"kept_{key}_pct"] = round(100.0 * kept / points_in, 3) if points_in else 0.0
            dens = [st.density_pct[key] for st in stats if key in st.density_pct]
            if dens:
                result[f"density_{key}_pct"] = round(float(np.mean(dens)), 4)
        dens_all = [st.density_all_pct for st in stats if st.density_all_pct is not None]
        if dens_all:
            result["density_all_pct"] = round(float(np.mean(dens_all)), 4)
        result["format"] = settings.fmt
        result["output"] = str(out_dir)
        return result


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


# -- the ring table ------------------------------------------------------------------------------


@dataclass(frozen=True)
class RingReport:
    """The ring table of one cloud: the method that recovered its rings and per-ring
    statistics (:class:`~sparsetools.ops.rings.RingTable`)."""

    cloud: str
    points: int
    n_lasers: int
    ring_method: str
    table: object

    def to_dict(self) -> dict:
        return {"cloud": self.cloud, "points": self.points, "n_lasers": self.n_lasers,
                "ring_method": self.ring_method, **self.table.as_dict()}  # fmt: skip

    def format(self) -> str:
        d = self.table.as_dict()
        order = "decreasing" if d["monotonic"] else "NOT monotonic"
        return (
            f"{self.cloud}: {self.points} points, {d['rings']} rings ({self.ring_method}, "
            f"{self.n_lasers} lasers), median elevation {order}\n{self.table.format()}"
        )


def ring_report(clouds: list[str | os.PathLike], settings: BeamsSettings) -> list[RingReport]:
    """Ring table of each cloud (files or folders): method used, rings, per-ring statistics."""
    from ..io.sources import cloud_frames

    out = []
    for f in cloud_frames(list(clouds)):
        points = read_points(f.cloud, strict=True)
        ring, used, n_lasers = recover_cloud_rings(points, f.cloud, settings)
        table = ring_table(points, ring, far_range=settings.far_range)
        out.append(RingReport(str(f.cloud), int(points.shape[0]), n_lasers, used, table))
    return out
