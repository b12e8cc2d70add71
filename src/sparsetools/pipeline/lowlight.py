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
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from ..errors import FormatError
from ..io.atomic import atomic_path
from ..io.sidecar import check_manifest_row, read_record_sidecar
from ..io.sources import Frame, FrameKey
from ..ops.lowlight import LowLightParams
from ..validate import check_int_range
from .batch import RunSummary
from .core import BatchJob, FrameStats, FrameTask

__all__ = [
    "MAX_VARIANTS",
    "LowLightInput",
    "LowLightJob",
    "LowLightSettings",
    "LowLightStats",
    "write_manifest",
]

log = logging.getLogger(__name__)

MANIFEST = "manifest.parquet"
RECORDS = "records"
#: Night versions per image at most (each is a full image on disk).
MAX_VARIANTS = 1000


@dataclass(frozen=True)
class LowLightSettings:
    """What a run's night images depend on (the same for every frame).

    Attributes
    ----------
    seed : int
        Global seed: output ``k`` of frame ``f`` draws from ``frame_rng(seed, "<f>:<k>")``.
    variants : int
        Night versions per image (1..:data:`MAX_VARIANTS`).
    params : LowLightParams
    """

    seed: int = 0
    variants: int = 1
    params: LowLightParams = field(default_factory=LowLightParams)

    def __post_init__(self) -> None:
        # the manifest's seed column is int64
        seed = check_int_range(self.seed, "seed", low=-(2**63), high=2**63 - 1)
        object.__setattr__(self, "seed", seed)
        object.__setattr__(
            self, "variants", check_int_range(self.variants, "variants", low=1, high=MAX_VARIANTS)
        )


@dataclass(frozen=True)
class LowLightInput:
    """One frame's files: the day image, its depth map and calibration (both optional)."""

    image: str
    depth: str | None = None
    calib: str | None = None


def _output_name(frame: str, variant: int, variants: int) -> str:
    return f"{frame}.png" if variants == 1 else f"{frame}_v{variant}.png"


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
class LowLightStats(FrameStats):
    """One source image: night images written, flares placed in them."""

    images: int
    flares: int


@dataclass(frozen=True)
class LowLightJob(BatchJob[LowLightInput]):
    """``sparsetools lowlight-synth`` (picklable): per image read, synthesise every variant,
    write the night PNGs and their record sidecars, then the manifest of all of them.

    The flare bank (about 1 s to build) comes from the on-disk cache of
    :func:`flare_cache_dir` (the same arrays, built once per machine and loaded in 0.1 s), so
    a process, and every worker of a pool, does not build its own.
    """

    command: ClassVar[str] = "lowlight-synth"
    noun: ClassVar[str] = "night images"
    stats_type: ClassVar[type[FrameStats]] = LowLightStats

    settings: LowLightSettings = field(default_factory=LowLightSettings)

    def tasks(self, frames: list[Frame], out_dir: Path) -> list[FrameTask[LowLightInput]]:
        """One task per source image (all its variants): ``OUT/<sequence>/<frame>[_v<k>].png``
        and the record sidecars ``OUT/records/<sequence>/<frame>[_v<k>].json``."""
        variants = self.settings.variants
        tasks = []
        for f in frames:
            outputs = {}
            for k in range(variants):
                stem = _output_name(f.key.frame, k, variants)[: -len(".png")]
                outputs[f"image{k}"] = FrameKey(f.key.sequence, stem).path(out_dir, ".png")
                outputs[f"record{k}"] = FrameKey(f.key.sequence, stem).path(
                    out_dir, ".json", prefix=RECORDS
                )
            if variants == 1:
                outputs = {"image": outputs["image0"], "record": outputs["record0"]}
            inp = LowLightInput(
                image=str(f.image),
                depth=None if f.depth is None else str(f.depth),
                calib=None if f.calib is None else str(f.calib),
            )
            sources = tuple(p for p in (f.image, f.depth, f.calib) if p is not None)
            tasks.append(FrameTask(f.key, inp, outputs, sources))
        return tasks

    def record(self) -> dict:
        s = self.settings
        return {"seed": s.seed, "variants": s.variants, **s.params.to_dict()}

    def option_names(self) -> dict:
        return {"camera": "--noise-profile"}

    def shared_outputs(self, out_dir: Path) -> tuple[Path, ...]:
        return (out_dir / MANIFEST,)

    def finish(self, summary: RunSummary, tasks: list, out_dir: Path) -> dict:
        """Rebuild the manifest; totals: ``images`` written, ``flares`` placed,
        ``manifest_rows``, ``manifest``."""
        _, rows = write_manifest(out_dir, tasks)
        stats = self.stats(summary)
        return {
            "images": sum(st.images for st in stats),
            "flares": sum(st.flares for st in stats),
            "manifest_rows": rows,
            "manifest": str(out_dir / MANIFEST),
        }

    def prepare(self) -> None:
        """Load what every frame uses (the noise model's SciPy, the flare bank, the codecs)
        with one tiny image: called once in the parent before a pool forks, so workers inherit
        it."""
        import numpy as np

        from ..io.image import import_cv2
        from ..ops.lowlight import lowlight

        import_cv2()
        params = self.settings.params
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
        doc = {"seed": s.seed, "variants": s.variants, "params": s.params.to_dict()}
        return json.loads(json.dumps(doc))

    def __call__(self, task: FrameTask[LowLightInput]) -> dict:
        from ..io.calib import frame_calibration
        from ..io.image import read_depth_png, read_image, write_image
        from ..ops.lowlight import lowlight
        from ..random import frame_rng

        inp, s = task.inputs, self.settings
        params = s.params
        image = read_image(inp.image)  # grey -> RGB; 16-bit refused with a clear message
        depth = read_depth_png(inp.depth) if inp.depth else None
        if depth is not None and depth.shape != image.shape[:2]:
            raise FormatError(
                f"{inp.depth}: depth map is {depth.shape[1]}x{depth.shape[0]} but "
                f"{Path(inp.image).name} is {image.shape[1]}x{image.shape[0]}"
            )
        # The flares' 3-D points need the intrinsics of THIS image: a calibration of other
        # images (another size, a principal point far from the centre) is refused.
        K = None
        if inp.calib:
            K = frame_calibration(calib_path=inp.calib, image=inp.image, what="image").K
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
        return LowLightStats(images=len(images), flares=flares)


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


#: The fields of a sidecar and their kinds (:func:`sparsetools.io.sidecar.check_fields`).
SIDECAR_FIELDS = {
    "output": "str", "source": "str", "depth": "str?", "calib": "str?", "frame_id": "str",
    "variant": "count", "seed": "int", "config": "dict", "record": "dict",
}  # fmt: skip


def _manifest_row(side_path: Path, frame_id: str, output: str, variant: int) -> dict:
    """A manifest row from a sidecar, every field checked: its kind, the record's own fields
    (as the typed record writes them), and that it is the record of this output."""
    from ..ops.lowlight import LowLightRecord

    expect = {"frame_id": frame_id, "output": output, "variant": variant}
    side, rec = read_record_sidecar(side_path, fields=SIDECAR_FIELDS, expect=expect,
                                    record_type=LowLightRecord, what="low-light record")  # fmt: skip
    return {
        "output": side["output"], "source": side["source"], "depth": side["depth"],
        "calib": side["calib"], "frame_id": side["frame_id"], "variant": side["variant"],
        "seed": side["seed"], "width": rec.width, "height": rec.height,
        **rec.summary(), "record_json": rec.to_json(),
    }  # fmt: skip


def write_manifest(out_dir: str | os.PathLike, tasks: list[FrameTask]) -> tuple[Path, int]:
    """Rebuild ``OUT/manifest.parquet`` from the sidecars of the complete tasks (atomic write).

    Returns the manifest path and its number of rows. Rows follow task order, then variant,
    so the file does not depend on the order in which workers finished.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = []
    schema = _manifest_schema()
    for t in tasks:
        if not all(Path(p).is_file() for p in t.outputs.values()):
            continue
        images, records = _images_and_records(t)
        for k, (img_path, side_path) in enumerate(zip(images, records, strict=True)):
            row = _manifest_row(side_path, t.frame_id, Path(img_path).name, k)
            check_manifest_row(row, schema, side_path)
            rows.append(row)
    table = pa.Table.from_pylist(rows, schema=schema)
    path = Path(out_dir) / MANIFEST
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)
    return path, len(rows)
