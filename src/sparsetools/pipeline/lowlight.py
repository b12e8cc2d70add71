"""Batch job of ``sparsetools lowlight-synth``: night images + a Parquet manifest.

Per source image and variant ``k`` the job draws a :class:`~sparsetools.ops.lowlight.LowLightRecord`
from ``frame_rng(seed, "<stem>:<k>")`` (so the output does not depend on ``--workers``), writes
the night image and a JSON sidecar ``records/<name>.json`` holding the record. After the
batch, ``manifest.parquet`` is rebuilt from all sidecars (frames done earlier included, so an
interrupted run resumes and still gets a complete manifest) and written atomically.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import FormatError, OutputError, ParameterError
from ..io.atomic import atomic_path
from ..io.sources import CALIB_SUFFIXES, IMAGE_SUFFIXES, find_by_stem
from .core import FrameTask, check_output_dir, run_frames

__all__ = [
    "LowLightJob",
    "collect_images",
    "lowlight_frame",
    "lowlight_tasks",
    "run_lowlight",
    "write_manifest",
]

log = logging.getLogger(__name__)

MANIFEST = "manifest.parquet"
RECORDS = "records"


def collect_images(paths) -> list[Path]:
    """Expand image files and folders (not recursive) into a sorted-per-folder list.

    Raises
    ------
    FormatError
        A path does not exist, a folder holds no image, or a file is not a PNG/JPEG.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(
                f for f in p.iterdir()
                if f.is_file() and not f.name.startswith(".") and f.suffix.lower() in IMAGE_SUFFIXES
            )  # fmt: skip
            if not found:
                raise FormatError(f"{p}: no images in this folder (looked for *.png, *.jpg)")
            out.extend(found)
        elif p.is_file():
            if p.suffix.lower() not in IMAGE_SUFFIXES:
                raise FormatError(f"{p}: not a PNG or JPEG image")
            out.append(p)
        else:
            raise FormatError(f"{p}: no such file or folder")
    if not out:
        raise ParameterError("no images given")
    return out


@dataclass(frozen=True)
class LowLightJob:
    """Settings shared by every frame (picklable)."""

    seed: int
    variants: int
    params: dict

    def config(self) -> dict:
        """JSON-normalised settings (tuples as lists), comparable with a sidecar's copy."""
        return json.loads(
            json.dumps({"seed": self.seed, "variants": self.variants, "params": self.params})
        )


def _output_name(stem: str, variant: int, variants: int) -> str:
    return f"{stem}.png" if variants == 1 else f"{stem}_v{variant}.png"


def lowlight_tasks(
    images,
    out_dir: str | os.PathLike,
    *,
    depth: str | os.PathLike | None = None,
    calib: str | os.PathLike | None = None,
    seed: int = 0,
    variants: int = 1,
    params=None,
) -> list[FrameTask]:
    """One task per source image (all its variants).

    Parameters
    ----------
    images : list of path-like
        Image files and/or folders.
    out_dir : path-like
    depth : path-like, optional
        A depth PNG (only with a single image) or a folder of ``<stem>.png`` depth maps.
    calib : path-like, optional
        A calibration shared by every frame, or a folder of per-frame ``<stem>.txt``/``.json``.
    seed, variants : int
    params : LowLightParams, optional
    """
    from ..ops.lowlight import LowLightParams

    params = params or LowLightParams()
    if variants < 1:
        raise ParameterError(f"variants must be >= 1, got {variants}")
    files = collect_images(images)
    depth_p = Path(depth) if depth is not None else None
    calib_p = Path(calib) if calib is not None else None
    if depth_p is not None and depth_p.is_file() and len(files) > 1:
        raise ParameterError(
            f"--depth {depth_p} is one file but {len(files)} images were given: pass a folder "
            "of <stem>.png depth maps"
        )
    per_frame_calib = (
        calib_p is not None
        and calib_p.is_dir()
        and not ((calib_p / "calib_cam_to_cam.txt").is_file())
    )
    job = LowLightJob(int(seed), int(variants), params.to_dict())
    out = Path(out_dir)
    tasks = []
    missing = []
    for f in files:
        stem = f.stem
        d = depth_p
        if depth_p is not None and depth_p.is_dir():
            d = depth_p / f"{stem}.png"
            if not d.is_file():
                missing.append(str(d))
        c = calib_p
        if per_frame_calib:
            c = find_by_stem(calib_p, stem, CALIB_SUFFIXES) or calib_p / f"{stem}.txt"
        names = [_output_name(stem, k, variants) for k in range(variants)]
        outputs = tuple(out / n for n in names) + tuple(
            out / RECORDS / (Path(n).stem + ".json") for n in names
        )
        tasks.append(FrameTask(stem, {
            "image": str(f), "depth": None if d is None else str(d),
            "calib": None if c is None else str(c), "job": job,
        }, outputs))  # fmt: skip
    if missing:
        more = f" (and {len(missing) - 3} more)" if len(missing) > 3 else ""
        raise FormatError(f"no depth map for some images: {', '.join(missing[:3])}{more}")
    return tasks


def lowlight_frame(task: FrameTask) -> dict:
    """Per-frame job: read, synthesise every variant, write PNGs and record sidecars."""
    from ..io.calib import load_calibration
    from ..io.image import read_depth_png, read_image, write_image
    from ..ops.lowlight import LowLightParams, lowlight
    from ..random import frame_rng

    inp = task.inputs
    job: LowLightJob = inp["job"]
    params = LowLightParams(**job.params)
    image = read_image(inp["image"])  # grey -> RGB; 16-bit refused with a clear message
    depth = read_depth_png(inp["depth"]) if inp["depth"] else None
    if depth is not None and depth.shape != image.shape[:2]:
        raise FormatError(
            f"{inp['depth']}: depth map is {depth.shape[1]}x{depth.shape[0]} but "
            f"{Path(inp['image']).name} is {image.shape[1]}x{image.shape[0]}"
        )
    K = load_calibration(inp["calib"]).K if inp["calib"] else None
    n_out = len(task.outputs) // 2
    flares = 0
    for k in range(n_out):
        rng = frame_rng(job.seed, f"{task.frame_id}:{k}")
        night, record = lowlight(image, depth=depth, K=K, rng=rng, params=params)
        write_image(task.outputs[k], night)
        row = {
            "output": Path(task.outputs[k]).name, "source": inp["image"], "depth": inp["depth"],
            "calib": inp["calib"], "frame_id": task.frame_id, "variant": k, "seed": job.seed,
            "config": job.config(), "record": record.to_dict(),
        }  # fmt: skip
        with atomic_path(task.outputs[n_out + k]) as tmp:
            tmp.write_text(json.dumps(row, sort_keys=True) + "\n", encoding="utf-8")
        flares += record.flare_count
    return {"images": n_out, "flares": flares}


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
        ("record_json", pa.string()),
    ])  # fmt: skip


def _read_sidecar(path: Path) -> dict:
    try:
        side = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(
            f"{path}: unreadable record sidecar ({exc}); rerun with --overwrite"
        ) from exc
    if not isinstance(side, dict):
        raise FormatError(f"{path}: not a record sidecar (a JSON object); rerun with --overwrite")
    return side


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
        n_out = len(t.outputs) // 2
        if not all(Path(p).is_file() for p in t.outputs):
            continue
        for k in range(n_out):
            side = _read_sidecar(Path(t.outputs[n_out + k]))
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


def _check_existing(out_dir: str | os.PathLike, job_config: dict, overwrite: bool) -> None:
    """Refuse to add to a folder holding outputs made with other settings (they would mix)."""
    if overwrite:
        return
    records = Path(out_dir) / RECORDS
    if not records.is_dir():
        return
    # Every run writes one configuration, so one sidecar tells which one the folder holds.
    for p in sorted(records.glob("*.json")):
        if p.name.startswith("."):  # a temporary file left by a killed run (removed later)
            continue
        if _read_sidecar(p).get("config") != job_config:
            raise OutputError(
                f"{out_dir} holds night images made with other settings (seed, variants or "
                "parameters); use --overwrite or another output folder"
            )
        return


def run_lowlight(
    images,
    out_dir: str | os.PathLike,
    *,
    depth=None,
    calib=None,
    seed: int = 0,
    variants: int = 1,
    params=None,
    executor=None,
    overwrite: bool = False,
    on_error: str = "stop",
    progress: bool | None = None,
) -> dict:
    """Synthesise night images for a batch; see :func:`lowlight_tasks` for the inputs.

    Returns
    -------
    dict
        Run summary (frames, processed, skipped, failed, seconds) plus ``images`` written,
        ``flares`` placed and ``manifest_rows``.
    """
    from ..ops.lowlight import LowLightParams

    params = params or LowLightParams()
    inputs = [*map(str, images)] + [str(p) for p in (depth, calib) if p is not None]
    check_output_dir(out_dir, inputs)
    tasks = lowlight_tasks(images, out_dir, depth=depth, calib=calib, seed=seed,
                           variants=variants, params=params)  # fmt: skip
    _check_existing(out_dir, tasks[0].inputs["job"].config(), overwrite)
    if calib is not None and depth is None:
        log.warning("--calib without --depth: the calibration is only used to place flares in 3-D")
    summary = run_frames(
        lowlight_frame,
        tasks,
        executor=executor,
        overwrite=overwrite,
        on_error=on_error,
        progress=progress,
        desc="lowlight",
    )
    _, rows = write_manifest(out_dir, tasks)
    out = summary.as_dict()
    out["images"] = int(summary.total("images"))
    out["flares"] = int(summary.total("flares"))
    out["manifest_rows"] = rows
    out["manifest"] = str(Path(out_dir) / MANIFEST)
    return out
