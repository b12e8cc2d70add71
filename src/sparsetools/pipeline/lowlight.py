"""Batch job of ``sparsetools lowlight-synth``: night images + a Parquet manifest.

Per source image and variant ``k`` the job draws a :class:`~sparsetools.ops.lowlight.LowLightRecord`
from ``frame_rng(seed, "<frame id>:<k>")`` (so the output does not depend on ``--workers``),
writes the night image ``OUT/<sequence>/<frame>[_v<k>].png`` and a JSON sidecar
``OUT/records/<sequence>/<frame>[_v<k>].json`` holding the record. After the
batch, ``manifest.parquet`` is rebuilt from all sidecars (frames done earlier included, so an
interrupted run resumes and still gets a complete manifest) and written atomically.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import FormatError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import IMAGE_SUFFIXES, Frame, FrameKey
from .batch import Batch, RunSummary
from .core import FrameTask, RunSpec, check_output_dir, run_frames

__all__ = [
    "MAX_VARIANTS",
    "LowLightInput",
    "LowLightJob",
    "LowLightSettings",
    "image_frames",
    "lowlight_tasks",
    "read_sidecar",
    "run_lowlight",
    "write_manifest",
]

log = logging.getLogger(__name__)

MANIFEST = "manifest.parquet"
RECORDS = "records"
#: Night versions per image at most (each is a full image on disk).
MAX_VARIANTS = 1000


def image_frames(paths, *, option: str = "IMAGE") -> list[Frame]:
    """Images given as files and/or folders (a folder tree: ``DIR/<sequence>/<frame>.png``;
    a folder written by sparsetools: its recorded images), as frames sorted by key.

    Raises
    ------
    FormatError
        A path does not exist, a folder holds no image, a file is not a PNG/JPEG, or two
        files are the same frame.
    """
    from ..io.sources import index_input, merge_frames

    paths = list(paths)
    if not paths:
        raise ParameterError("no images given")

    def index(p: Path):
        if p.is_file() and p.suffix.lower() not in IMAGE_SUFFIXES:
            raise FormatError(f"{p}: not a PNG or JPEG image")
        return index_input(p, "image", option=option)

    return merge_frames((index(p) for p in map(Path, paths)), "image")


@dataclass(frozen=True)
class LowLightSettings:
    """What a run's night images depend on (the same for every frame)."""

    seed: int
    variants: int
    params: dict


@dataclass(frozen=True)
class LowLightInput:
    """One frame's files: the day image, its depth map and calibration (both optional)."""

    image: str
    depth: str | None = None
    calib: str | None = None


def _output_name(frame: str, variant: int, variants: int) -> str:
    return f"{frame}.png" if variants == 1 else f"{frame}_v{variant}.png"


def lowlight_tasks(
    frames: list[Frame], out_dir: str | os.PathLike, settings: LowLightSettings
) -> list[FrameTask[LowLightInput]]:
    """One task per source image (all its variants): ``OUT/<sequence>/<frame>[_v<k>].png``
    and the record sidecars ``OUT/records/<sequence>/<frame>[_v<k>].json``."""
    out = Path(out_dir)
    tasks = []
    for f in frames:
        outputs = {}
        for k in range(settings.variants):
            name = _output_name(f.key.frame, k, settings.variants)
            stem = name[: -len(".png")]
            outputs[f"image{k}"] = FrameKey(f.key.sequence, stem).path(out, ".png")
            outputs[f"record{k}"] = FrameKey(f.key.sequence, stem).path(
                out, ".json", prefix=RECORDS
            )
        if settings.variants == 1:
            outputs = {"image": outputs["image0"], "record": outputs["record0"]}
        inp = LowLightInput(
            image=str(f.image),
            depth=None if f.depth is None else str(f.depth),
            calib=None if f.calib is None else str(f.calib),
        )
        sources = tuple(p for p in (f.image, f.depth, f.calib) if p is not None)
        tasks.append(FrameTask(f.key, inp, outputs, sources))
    return tasks


def _images_and_records(task: FrameTask) -> tuple[list[Path], list[Path]]:
    roles = list(task.outputs)
    images = [task.outputs[r] for r in roles if r.startswith("image")]
    records = [task.outputs[r] for r in roles if r.startswith("record")]
    return images, records


def flare_cache_dir() -> Path | None:
    """Where flare banks are kept between runs: ``SPARSETOOLS_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/sparsetools``, else ``~/.cache/sparsetools``; None when it cannot be
    written (each process then builds its bank in memory)."""
    base = os.environ.get("SPARSETOOLS_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "sparsetools",
    )
    try:
        os.makedirs(base, exist_ok=True)
    except OSError:
        return None
    return Path(base) if os.access(base, os.W_OK | os.X_OK) else None


@dataclass(frozen=True)
class LowLightJob:
    """The per-frame job of ``lowlight-synth`` (picklable): read, synthesise every variant,
    write the night PNGs and their record sidecars.

    The flare bank (about 1 s to build) comes from the on-disk cache of
    :func:`flare_cache_dir` (the same arrays, built once per machine and loaded in 0.1 s), so
    a process, and every worker of a pool, does not build its own.
    """

    settings: LowLightSettings

    def prepare(self) -> None:
        """Load what every frame uses (the noise model's SciPy, the flare bank, the codecs)
        with one tiny image: called once in the parent before a pool forks, so workers inherit
        it."""
        import numpy as np

        from ..io.image import import_cv2
        from ..ops.lowlight import LowLightParams, lowlight

        import_cv2()
        params = LowLightParams(**self.settings.params)
        lowlight(np.zeros((8, 8, 3), np.uint8), rng=0, params=params, bank=self.flare_bank(params))

    def flare_bank(self, params):
        """The bank ``params`` names, from the cache folder (None: lowlight builds it)."""
        folder = flare_cache_dir() if params.flare else None
        if folder is None:
            return None
        from ..io.flare_bank import cached_flare_bank

        return cached_flare_bank(
            folder, seed=params.bank_seed, count=params.bank_count, size=params.bank_size
        )

    def config(self) -> dict:
        """JSON-normalised settings (tuples as lists), as stored in every sidecar."""
        s = self.settings
        return json.loads(json.dumps({"seed": s.seed, "variants": s.variants, "params": s.params}))

    def __call__(self, task: FrameTask[LowLightInput]) -> dict:
        from ..io.calib import load_calibration
        from ..io.image import read_depth_png, read_image, write_image
        from ..ops.lowlight import LowLightParams, lowlight
        from ..random import frame_rng

        inp, s = task.inputs, self.settings
        params = LowLightParams(**s.params)
        image = read_image(inp.image)  # grey -> RGB; 16-bit refused with a clear message
        depth = read_depth_png(inp.depth) if inp.depth else None
        if depth is not None and depth.shape != image.shape[:2]:
            raise FormatError(
                f"{inp.depth}: depth map is {depth.shape[1]}x{depth.shape[0]} but "
                f"{Path(inp.image).name} is {image.shape[1]}x{image.shape[0]}"
            )
        K = load_calibration(inp.calib).K if inp.calib else None
        images, records = _images_and_records(task)
        flares = 0
        config = self.config()
        bank = self.flare_bank(params)
        for k, (img_out, rec_out) in enumerate(zip(images, records, strict=True)):
            rng = frame_rng(s.seed, f"{task.frame_id}:{k}")
            night, record = lowlight(image, depth=depth, K=K, rng=rng, params=params, bank=bank)
            write_image(img_out, night)
            row = {
                "output": img_out.name, "source": inp.image, "depth": inp.depth,
                "calib": inp.calib, "frame_id": task.frame_id, "variant": k, "seed": s.seed,
                "config": config, "record": record.to_dict(),
            }  # fmt: skip
            with atomic_path(rec_out) as tmp:
                tmp.write_text(json.dumps(row, sort_keys=True) + "\n", encoding="utf-8")
            flares += record.flare_count
        return {"images": len(images), "flares": flares}


def _manifest_schema():
    import pyarrow as pa

    return pa.schema([
        ("output", pa.string()), ("source", pa.string()), ("depth", pa.string()),
        ("calib", pa.string()), ("frame_id", pa.string()), ("variant", pa.int32()),
        ("seed", pa.int64()), ("width", pa.int32()), ("height", pa.int32()),
        ("brightness", pa.float64()), ("gamma", pa.float64()), ("flare_source", pa.string()),
        ("flare_scale", pa.float64()), ("flare_amount", pa.float64()),
        ("flare_count", pa.int32()), ("flare_u", pa.list_(pa.int32())),
        ("flare_v", pa.list_(pa.int32())), ("flare_depth", pa.list_(pa.float64())),
        ("flare_pattern", pa.list_(pa.int32())), ("noise_model", pa.string()),
        ("camera", pa.string()), ("system_gain", pa.float64()), ("ratio", pa.float64()),
        ("saturation", pa.float64()), ("tukey_lambda", pa.float64()),
        ("sigma_read", pa.float64()), ("sigma_row", pa.float64()), ("noise_seed", pa.int64()),
        ("color_bias", pa.list_(pa.float64())), ("noise_table_row", pa.int32()),
        ("record_json", pa.string()),
    ])  # fmt: skip


def read_sidecar(path: str | os.PathLike) -> dict:
    """The JSON object of a record sidecar (``OUT/records/...json``).

    Raises
    ------
    FormatError
        Unreadable, not JSON, or not an object.
    """
    path = Path(path)
    try:
        side = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(
            f"{path}: unreadable record sidecar ({exc}); rerun with --overwrite"
        ) from exc
    if not isinstance(side, dict):
        raise FormatError(f"{path}: not a record sidecar (a JSON object); rerun with --overwrite")
    return side


_read_sidecar = read_sidecar  # the name tests/robustness/test_fuzz.py imports


def write_manifest(out_dir: str | os.PathLike, tasks: list[FrameTask]) -> tuple[Path, int]:
    """Rebuild ``OUT/manifest.parquet`` from the sidecars of the complete tasks (atomic write).

    Returns the manifest path and its number of rows. Rows follow task order, then variant,
    so the file does not depend on the order in which workers finished.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    from ..ops.lowlight import LowLightRecord

    rows = []
    for t in tasks:
        if not all(Path(p).is_file() for p in t.outputs.values()):
            continue
        for side_path in _images_and_records(t)[1]:
            side = read_sidecar(side_path)
            rec = LowLightRecord.from_dict(side["record"])
            rows.append({
                "output": side["output"], "source": side["source"], "depth": side["depth"],
                "calib": side["calib"], "frame_id": side["frame_id"], "variant": side["variant"],
                "seed": side["seed"], "width": rec.width, "height": rec.height,
                **rec.summary(), "record_json": rec.to_json(),
            })  # fmt: skip
    table = pa.Table.from_pylist(rows, schema=_manifest_schema())
    path = Path(out_dir) / MANIFEST
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path, len(rows)


def run_lowlight(
    images,
    out_dir: str | os.PathLike,
    *,
    depth=None,
    calib=None,
    seed: int = 0,
    variants: int = 1,
    params=None,
    batch: Batch | None = None,
) -> RunSummary:
    """Synthesise night images for a batch.

    Parameters
    ----------
    images : list of path-like
        Image files and/or folders.
    out_dir : path-like
    depth : path-like, optional
        A depth PNG (only with a single image) or a folder of depth maps matched by frame.
    calib : path-like, optional
        A calibration shared by every frame, or a folder of per-frame files.
    seed, variants : int
    params : LowLightParams, optional
    batch : Batch, optional

    Returns
    -------
    RunSummary
        Totals: ``images`` written, ``flares`` placed, ``manifest_rows``, ``manifest``.
    """
    from ..io.sources import attach
    from ..ops.lowlight import LowLightParams
    from ..validate import check_int_range

    batch = batch or Batch()
    params = params or LowLightParams()
    check_int_range(variants, "variants", low=1, high=MAX_VARIANTS)
    frames = image_frames(images)
    frames, missing = attach(
        frames, depth, "depth", role="depth", option="--depth", shared_ok=False
    )
    if missing:
        absent = [str(f.depth) for f in frames if not Path(f.depth).is_file()]
        more = f" (and {len(absent) - 3} more)" if len(absent) > 3 else ""
        raise FormatError(f"no depth map for some images: {', '.join(absent[:3])}{more}")
    frames, _ = attach(frames, calib, "calib", role="calib", option="--calib")
    inputs = [*map(str, images)] + [str(p) for p in (depth, calib) if p is not None]
    out = check_output_dir(out_dir, inputs)
    settings = LowLightSettings(int(seed), int(variants), params.to_dict())
    tasks = lowlight_tasks(frames, out, settings)
    if calib is not None and depth is None:
        log.warning("--calib without --depth: the calibration is only used to place flares in 3-D")
    spec = RunSpec(
        "lowlight-synth", out, {"seed": settings.seed, "variants": settings.variants,
                                **settings.params},
        noun="night images", shared_outputs=(out / MANIFEST,),
    )  # fmt: skip
    summary = run_frames(LowLightJob(settings), tasks, batch=batch, spec=spec, desc="lowlight")
    _, rows = write_manifest(out, tasks)
    return summary.with_totals(
        {
            "images": int(summary.total("images")),
            "flares": int(summary.total("flares")),
            "manifest_rows": rows,
            "manifest": str(out / MANIFEST),
        }
    )
