"""Batch job of ``sparsetools defocus-synth``: defocused images, radius maps, records, manifest.

Per frame the job reads the sharp image and its dense depth (and, with ``--calib``, the
calibration whose ``K[0, 0]`` gives the focal length in pixels), draws the sampled values from
``frame_rng(seed, "<frame id>")`` (so the output does not depend on ``--workers``) and writes

- ``OUT/<sequence>/<frame>.png``: the defocused image (8-bit RGB);
- ``OUT/radius/<sequence>/<frame>.npy``: the blur radius ``r(d)`` of every pixel, (H, W)
  float32 pixels, unquantised and unclipped (``r(inf)`` where depth is missing); with
  ``--radius-format png`` instead ``.png``, uint16 ``round(r * 256)`` (radii of 256 px or
  more saturate at 65535 and are counted);
- ``OUT/records/<sequence>/<frame>.json``: the inputs, the run's settings and the complete
  :class:`~sparsetools.ops.defocus.DefocusRecord`, from which
  ``defocus(image, depth, record=...)`` reproduces the image bit for bit.

After the batch ``manifest.parquet`` (one row per image, every sampled value as a column plus
the record as JSON) is rebuilt from all sidecars, frames done by earlier runs included, and
written atomically.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sidecar import check_manifest_row, read_record_sidecar
from ..io.sources import Frame
from ..validate import check_choice, check_int_range, check_pair, check_positive
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask

__all__ = [
    "MANIFEST",
    "RADIUS_DIR",
    "RADIUS_FORMATS",
    "RADIUS_PNG_SCALE",
    "RECORDS",
    "DefocusInput",
    "DefocusJob",
    "DefocusSettings",
    "DefocusStats",
    "write_defocus_manifest",
]

MANIFEST = "manifest.parquet"
RECORDS = "records"
RADIUS_DIR = "radius"
RADIUS_FORMATS = ("npy", "png")
#: A radius PNG stores ``round(r * 256)`` (the KITTI depth PNG scale): 1/256 px steps.
RADIUS_PNG_SCALE = 256.0


@dataclass(frozen=True)
class DefocusSettings:
    """What the defocused images depend on (the same for every frame).

    Attributes
    ----------
    seed : int
        Global seed; frame ``k`` draws from ``frame_rng(seed, str(key))``.
    sensor : str
        Lens preset (:data:`sparsetools.ops.defocus.DEFOCUS_CAMERAS`, ``--lens``): focal
        length, f-number and pixel pitch, each replaced by an explicit value when one is given.
    focal_length_mm : float, optional
        Focal length ``f``, millimetres.
    f_number : (float, float), optional
        ``F_n ~ logU(low, high)`` per image (equal bounds: fixed).
    pixel_pitch_um : float, optional
        Pixel pitch ``p_x`` of the images blurred, micrometres.
    calib : bool
        The focal length comes from each frame's calibration: ``f = K[0, 0] * p_x``.
    focus_distance : (float, float), metres
        ``D_fp ~ logU(low, high)`` per image (equal bounds: fixed).
    blur_kernel : {"disk", "gaussian"}
    layer_step, max_radius : float, pixels
    missing_depth : {"error", "far"}
        Depth 0 / non-finite: refuse the frame, or render the pixel as infinitely far.
    noise : {"none", "eld", "gaussian"}
        ELD sensor noise after the blur.
    camera : str
        ELD noise table (``--noise-profile``; ``random``: one per image).
    ratio : (float, float)
        Exposure ratio of the noise, ``~ logU``.
    noise_gamma : float
        Linearisation exponent around the noise.
    color_bias : bool
        Add the noise table's per-channel black-level offsets.
    radius_format : {"npy", "png"}
        Encoding of the radius maps (module docstring).
    """

    seed: int = 0
    sensor: str = field(default="dfd-nyu", metadata={"option": "--lens"})
    focal_length_mm: float | None = None
    f_number: tuple[float, float] | None = None
    pixel_pitch_um: float | None = None
    calib: bool = False
    focus_distance: tuple[float, float] = (0.7, 0.7)
    blur_kernel: str = "disk"
    layer_step: float = 0.5
    max_radius: float = 64.0
    missing_depth: str = "error"
    noise: str = "none"
    camera: str = field(default="SonyA7S2", metadata={"option": "--noise-profile"})
    ratio: tuple[float, float] = (1.0, 8.0)
    noise_gamma: float = 2.2
    color_bias: bool = False
    radius_format: str = "npy"

    def __post_init__(self) -> None:
        from ..ops.defocus import DEFOCUS_CAMERAS

        set_ = object.__setattr__  # frozen: normalise once
        # the manifest's seed column is int64
        set_(self, "seed", check_int_range(self.seed, "seed", low=-(2**63), high=2**63 - 1))
        check_choice(self.sensor, "lens", DEFOCUS_CAMERAS)
        check_positive(self.focal_length_mm, "focal_length_mm", allow_none=True)
        check_positive(self.pixel_pitch_um, "pixel_pitch_um", allow_none=True)
        if self.calib and self.focal_length_mm is not None:
            raise ParameterError(
                "give the focal length either in millimetres or through --calib, not both",
                param="focal_length_mm",
            )
        if self.f_number is not None:
            set_(self, "f_number", check_pair(self.f_number, "f_number", low=0, strict=True))
        set_(self, "focus_distance",
             check_pair(self.focus_distance, "focus_distance", low=0, strict=True))  # fmt: skip
        set_(self, "ratio", check_pair(self.ratio, "ratio", low=0, strict=True))
        check_choice(self.radius_format, "radius_format", RADIUS_FORMATS)
        if not self.calib:  # with a calibration the focal length is known per frame only
            f_m = self.optics().focal_length_m
            if self.focus_distance[0] <= f_m:
                raise ParameterError(
                    f"{self.focus_distance[0]:g} m must exceed the focal length ({f_m:g} m)",
                    param="focus_distance",
                )
        # DefocusParams checks the rest (kernel, steps, noise model and table); with a
        # calibration a 1 px focal length (micrometres) stands in for the frames' own.
        self.params(1.0 if self.calib else None)

    def optics(self, focal_length_px: float | None = None):
        """The lens and sensor: the preset with the explicit values put in.

        Parameters
        ----------
        focal_length_px : float, optional
            ``K[0, 0]`` of the frame's calibration, pixels (with ``calib``).

        Returns
        -------
        CameraOptics
        """
        from ..ops.defocus import DEFOCUS_CAMERAS, CameraOptics

        preset = DEFOCUS_CAMERAS[self.sensor]
        pitch_m = preset.pixel_pitch_m if self.pixel_pitch_um is None else self.pixel_pitch_um / 1e6
        # A sampled f-number replaces this one in every record; it only has to be valid.
        f_number = preset.f_number if self.f_number is None else self.f_number[0]
        if focal_length_px is not None:
            return CameraOptics.from_calibration(
                focal_length_px, pixel_pitch_m=pitch_m, f_number=f_number
            )
        if self.focal_length_mm is None and self.pixel_pitch_um is None and self.f_number is None:
            return preset
        f_m = preset.focal_length_m if self.focal_length_mm is None else self.focal_length_mm / 1e3
        return CameraOptics(
            f"{self.sensor}, explicit values", f_m, f_number, pitch_m,
            f"--lens {self.sensor} with the values given on the command line",
        )  # fmt: skip

    def params(self, focal_length_px: float | None = None):
        """:class:`~sparsetools.ops.defocus.DefocusParams` of one frame."""
        from ..ops.defocus import DefocusParams

        return DefocusParams(
            camera=self.optics(focal_length_px), focus_distance=self.focus_distance,
            f_number=self.f_number, kernel=self.blur_kernel, layer_step=self.layer_step,
            max_radius=self.max_radius, missing=self.missing_depth, noise=self.noise,
            noise_camera=self.camera, ratio=self.ratio, noise_gamma=self.noise_gamma,
            color_bias=self.color_bias,
        )  # fmt: skip

    def to_dict(self) -> dict:
        """JSON-normalised settings (tuples as lists), as stored in every sidecar."""
        return json.loads(json.dumps(asdict(self)))


@dataclass(frozen=True)
class DefocusInput:
    """One frame's files: the sharp image, its dense depth, its calibration (optional)."""

    image: str
    depth: str
    calib: str | None = None
    out_dir: str = "."


def _write_radius(path: Path, radius: np.ndarray, fmt: str) -> int:
    """Write the radius map; returns the pixels saturated by the PNG encoding."""
    import cv2

    with atomic_path(path) as tmp:
        if fmt == "npy":
            with open(tmp, "wb") as fh:
                np.save(fh, radius.astype(np.float32))
            return 0
        scaled = np.rint(radius.astype(np.float64) * RADIUS_PNG_SCALE)
        saturated = int(np.count_nonzero(scaled > 65535))
        ok, buf = cv2.imencode(".png", np.clip(scaled, 0, 65535).astype(np.uint16))
        if not ok:  # pragma: no cover - OpenCV always encodes uint16 PNG
            raise FormatError(f"{path}: OpenCV failed to encode the radius PNG")
        tmp.write_bytes(buf.tobytes())
        return saturated


def _focal_length_px(inp: DefocusInput) -> float:
    """``K[0, 0]`` of the frame's calibration, checked against its image."""
    from ..io.calib import frame_calibration

    return float(frame_calibration(calib_path=inp.calib, image=inp.image, what="image").K[0, 0])


def _relative(path: Path, out: Path) -> str:
    return Path(os.path.relpath(path, out)).as_posix()


@dataclass(frozen=True)
class DefocusStats(FrameStats):
    """One image: images written (1), pixels without depth (rendered infinitely far), the
    largest and mean blur radius (pixels), radii saturated by the PNG encoding."""

    images: int
    far_pixels: int
    radius_max: float
    radius_mean: float
    radius_saturated: int


@dataclass(frozen=True)
class DefocusJob(BatchJob[DefocusInput]):
    """``sparsetools defocus-synth`` (picklable): per image read, defocus, write the image,
    the radius map and the record sidecar; then the manifest of all of them."""

    command: ClassVar[str] = "defocus-synth"
    noun: ClassVar[str] = "defocused images"
    stats_type: ClassVar[type[FrameStats]] = DefocusStats

    settings: DefocusSettings = field(default_factory=DefocusSettings)

    def planned(self, frames: list[Frame]) -> DefocusJob:
        """With calibrations the focal length comes from them (``settings.calib``)."""
        if not frames:
            raise ParameterError("no images given")
        has_calib = frames[0].calib is not None
        if has_calib and not self.settings.calib:
            return replace(self, settings=replace(self.settings, calib=True))
        if not has_calib and self.settings.calib:
            raise ParameterError("settings say the focal length comes from a calibration: give "
                                 "one", param="calib")  # fmt: skip
        return self

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[DefocusInput]]:
        """One task per frame: roles ``image``, ``radius`` and ``record`` (module docstring)."""
        suffix = "." + self.settings.radius_format
        tasks = []
        for f in frames:
            outputs = {
                "image": f.key.path(out_dir, ".png"),
                "radius": f.key.path(out_dir, suffix, prefix=RADIUS_DIR),
                "record": f.key.path(out_dir, ".json", prefix=RECORDS),
            }
            inp = DefocusInput(str(f.image), str(f.depth),
                               None if f.calib is None else str(f.calib), str(out_dir))  # fmt: skip
            sources = tuple(p for p in (f.image, f.depth, f.calib) if p is not None)
            tasks.append(FrameTask(f.key, inp, outputs, sources))
        return tasks

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / MANIFEST,)

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Rebuild the manifest; totals: ``images``, ``far_pixels``, ``radius_max`` (over the
        run), ``radius_saturated``, ``manifest_rows``, ``manifest``."""
        _, rows = write_defocus_manifest(out_dir, tasks)
        stats = self.stats(summary)
        return {
            "images": sum(st.images for st in stats),
            "far_pixels": sum(st.far_pixels for st in stats),
            "radius_max": max((st.radius_max for st in stats), default=0.0),
            "radius_saturated": sum(st.radius_saturated for st in stats),
            "manifest_rows": rows,
            "manifest": str(out_dir / MANIFEST),
        }

    def __call__(self, task: FrameTask[DefocusInput]) -> DefocusStats:
        from ..io.depth_files import read_depth_file
        from ..io.image import read_image, write_image
        from ..ops.defocus import defocus
        from ..random import frame_rng

        inp, s = task.inputs, self.settings
        image = read_image(inp.image)  # grey -> RGB; 16-bit refused with a clear message
        depth = read_depth_file(inp.depth)
        h, w = image.shape[:2]
        if depth.shape != (h, w):
            raise FormatError(
                f"{inp.depth}: depth map is {depth.shape[1]}x{depth.shape[0]} but "
                f"{Path(inp.image).name} is {w}x{h}"
            )
        holes = int(np.count_nonzero(~(np.isfinite(depth) & (depth > 0))))
        if holes and s.missing_depth == "error":
            raise FormatError(
                f"{inp.depth}: no depth at {holes} of {h * w} pixels: fill the holes, or give "
                "--missing-depth far to render them as infinitely far"
            )
        f_px = _focal_length_px(inp) if inp.calib else None
        params = s.params(f_px)
        blurred, radius, record = defocus(
            image, depth, rng=frame_rng(s.seed, task.frame_id), params=params
        )
        write_image(task.outputs["image"], blurred)
        saturated = _write_radius(task.outputs["radius"], radius, s.radius_format)
        out = Path(inp.out_dir)
        side = {
            "output": _relative(task.outputs["image"], out),
            "radius": _relative(task.outputs["radius"], out),
            "source": inp.image, "depth": inp.depth, "calib": inp.calib,
            "frame_id": task.frame_id, "seed": s.seed, "config": s.to_dict(),
            "record": record.to_dict(),
        }  # fmt: skip
        with atomic_path(task.outputs["record"]) as tmp:
            tmp.write_text(json.dumps(side, sort_keys=True) + "\n", encoding="utf-8")
        return DefocusStats(
            images=1,
            far_pixels=holes,
            radius_max=float(radius.max()),
            radius_mean=float(radius.mean(dtype=np.float64)),
            radius_saturated=saturated,
        )


def _manifest_schema():
    import pyarrow as pa

    return pa.schema([
        ("output", pa.string()), ("radius", pa.string()), ("source", pa.string()),
        ("depth", pa.string()), ("calib", pa.string()), ("frame_id", pa.string()),
        ("seed", pa.int64()), ("width", pa.int32()), ("height", pa.int32()),
        ("camera", pa.string()), ("focal_length_m", pa.float64()),
        ("pixel_pitch_m", pa.float64()), ("f_number", pa.float64()),
        ("focus_distance_m", pa.float64()), ("radius_scale", pa.float64()),
        ("kernel", pa.string()), ("layer_step", pa.float64()), ("max_radius", pa.float64()),
        ("missing", pa.string()), ("noise_model", pa.string()), ("noise_camera", pa.string()),
        ("system_gain", pa.float64()), ("ratio", pa.float64()), ("saturation", pa.float64()),
        ("tukey_lambda", pa.float64()), ("sigma_read", pa.float64()),
        ("sigma_row", pa.float64()), ("noise_seed", pa.int64()),
        ("color_bias", pa.list_(pa.float64())), ("noise_table_row", pa.int32()),
        ("noise_gamma", pa.float64()), ("record_json", pa.string()),
    ])  # fmt: skip


#: The fields of a sidecar and their kinds (:func:`sparsetools.io.sidecar.check_fields`).
SIDECAR_FIELDS = {
    "output": "str", "radius": "str", "source": "str", "depth": "str", "calib": "str?",
    "frame_id": "str", "seed": "int", "config": "dict", "record": "dict",
}  # fmt: skip


def _manifest_row(side_path: Path, expect: dict) -> dict:
    """A manifest row from a sidecar, every field checked: its kind, the record's own fields
    (as the typed record writes them), and that it is the record of this output."""
    from ..ops.defocus import DefocusRecord

    side, rec = read_record_sidecar(side_path, fields=SIDECAR_FIELDS, expect=expect,
                                    record_type=DefocusRecord, what="defocus record")  # fmt: skip
    n = rec.noise
    flat = {f.name: getattr(rec, f.name) for f in fields(rec) if f.name not in ("noise", "version")}
    return {
        "output": side["output"], "radius": side["radius"], "source": side["source"],
        "depth": side["depth"], "calib": side["calib"], "frame_id": side["frame_id"],
        "seed": side["seed"], **flat, "radius_scale": rec.radius_scale,
        "noise_model": n.model, "noise_camera": n.camera, "system_gain": n.system_gain,
        "ratio": n.ratio, "saturation": n.saturation, "tukey_lambda": n.tukey_lambda,
        "sigma_read": n.sigma_read, "sigma_row": n.sigma_row, "noise_seed": n.seed,
        "color_bias": list(n.color_bias), "noise_table_row": n.table_row,
        "record_json": rec.to_json(),
    }  # fmt: skip


def write_defocus_manifest(out_dir: str | os.PathLike, tasks: list[FrameTask]) -> tuple[Path, int]:
    """Rebuild ``OUT/manifest.parquet`` from the sidecars of the complete tasks (atomic write).

    Returns the manifest path and its number of rows (task order, so the file does not
    depend on the order in which workers finished).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = []
    schema = _manifest_schema()
    out = Path(out_dir)
    for t in tasks:
        if all(Path(p).is_file() for p in t.outputs.values()):
            side_path = Path(t.outputs["record"])
            expect = {"frame_id": t.frame_id, "output": _relative(t.outputs["image"], out),
                      "radius": _relative(t.outputs["radius"], out)}  # fmt: skip
            row = _manifest_row(side_path, expect)
            check_manifest_row(row, schema, side_path)
            rows.append(row)
    table = pa.Table.from_pylist(rows, schema=schema)
    path = Path(out_dir) / MANIFEST
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path, len(rows)
