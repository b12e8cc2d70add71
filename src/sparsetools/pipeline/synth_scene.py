"""``synth-scene``: make a synthetic scene or video folder, or keep it when it is up to date.

The generators (:mod:`sparsetools.synth`) write a whole folder at once; this module applies the
resume rule to it (:class:`~sparsetools.pipeline.output_file.OutputTree`): the same options on a
folder they made -> nothing to do; other options -> refused naming the first one that differs;
a non-empty folder they did not make -> refused (``--overwrite`` replaces it).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..io.provenance import RECORD_DIR
from .output_file import OutputTree

__all__ = ["run_synth_scene", "run_synth_video"]


def _files(out: Path) -> list[Path]:
    return [p for p in out.rglob("*") if p.is_file() and RECORD_DIR not in p.parts]


def _run(out_dir, command_settings: dict, noun: str, overwrite: bool, make) -> dict:
    out = Path(out_dir)
    tree = OutputTree(out, "synth-scene", command_settings, noun=noun, overwrite=overwrite)
    if tree.up_to_date():
        return {"out_dir": str(out), "up_to_date": True, "files": len(_files(out))}
    ours = out.is_dir() and (out / RECORD_DIR / "run.json").is_file()
    summary = make(overwrite or ours)  # an interrupted run of ours is finished in place
    tree.record(_files(out))
    return summary


def run_synth_scene(
    out_dir: str | os.PathLike,
    *,
    seed: int,
    frames: int,
    width: int,
    height: int,
    underwater_frames: int,
    stem_prefix: str = "",
    overwrite: bool = False,
) -> dict:
    """:func:`sparsetools.synth.generate_scene` under the resume rule; its summary, or
    ``{"up_to_date": True, ...}``."""
    from ..synth import generate_scene

    settings = {"mode": "street", "seed": seed, "frames": frames,
                "image_size": f"{width}x{height}", "underwater_frames": underwater_frames,
                "stem_prefix": stem_prefix}  # fmt: skip
    return _run(
        out_dir,
        settings,
        "a synthetic scene",
        overwrite,
        lambda ow: generate_scene(
            out_dir,
            seed=seed,
            frames=frames,
            width=width,
            height=height,
            underwater_frames=underwater_frames,
            overwrite=ow,
            stem_prefix=stem_prefix,
        ),
    )


def run_synth_video(out_dir: str | os.PathLike, *, overwrite: bool = False, **options) -> dict:
    """:func:`sparsetools.synth.video_files.write_video` under the resume rule (``options``:
    its keyword arguments; ``workers`` does not change the bytes and is not a setting)."""
    from ..synth.video_files import write_video

    settings = {"mode": "video", **{k: v for k, v in options.items() if k != "workers"}}
    return _run(
        out_dir,
        settings,
        "synthetic videos",
        overwrite,
        lambda ow: write_video(out_dir, overwrite=ow, **options),
    )
