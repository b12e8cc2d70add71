"""Check that a scene folder is exactly what the generator makes from its recorded seed."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from ..errors import FormatError

__all__ = ["compare_trees", "regenerate_and_compare"]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _scene_file(p: Path) -> bool:
    return p.is_file() and ".sparsetools" not in p.parts


def compare_trees(reference: str | os.PathLike, candidate: str | os.PathLike) -> dict:
    """Compare two folders file by file (SHA-256).

    Returns
    -------
    dict
        ``files`` compared, ``identical`` count, and lists ``missing`` (in reference only),
        ``extra`` (in candidate only) and ``different`` (relative paths).
    """
    ref, cand = Path(reference), Path(candidate)
    # the folder's record of what made it (.sparsetools/) is not part of the scene
    a = {p.relative_to(ref).as_posix() for p in ref.rglob("*") if _scene_file(p)}
    b = {p.relative_to(cand).as_posix() for p in cand.rglob("*") if _scene_file(p)}
    common = sorted(a & b)
    different = [rel for rel in common if _digest(ref / rel) != _digest(cand / rel)]
    return {
        "files": len(a),
        "identical": len(common) - len(different),
        "missing": sorted(a - b),
        "extra": sorted(b - a),
        "different": different,
    }


def regenerate_and_compare(reference: str | os.PathLike, out_dir: str | os.PathLike) -> dict:
    """Regenerate ``reference`` (a ``synth-scene`` folder) into ``out_dir`` from its
    ``scene.json`` parameters (``video.json`` for a ``--video`` folder) and compare the two
    byte for byte."""
    from .scene import generate_scene

    ref = Path(reference)
    if (ref / "video.json").is_file():
        return _regenerate_video(ref, out_dir)
    try:
        meta = json.loads((ref / "scene.json").read_text(encoding="utf-8"))
        seed, frames = int(meta["seed"]), int(meta["frames"])
        cam = meta["rig"]["camera"]
        width, height = int(cam["width"]), int(cam["height"])
        uw = meta.get("underwater") or {}
        uw_frames = int(uw.get("seafloor_frames", 0))
        uw_size = tuple(uw.get("size", (160, 120)))
    except FileNotFoundError as exc:
        raise FormatError(f"{ref}: no scene.json (not a synth-scene folder)") from exc
    except (KeyError, ValueError, TypeError, json.JSONDecodeError) as exc:
        raise FormatError(
            f"{ref}/scene.json: missing or invalid generation parameters ({exc})"
        ) from exc
    generate_scene(
        out_dir,
        seed=seed,
        frames=frames,
        width=width,
        height=height,
        underwater_frames=uw_frames,
        underwater_size=uw_size,
        overwrite=True,
        stem_prefix=str(meta.get("stem_prefix", "")),
    )
    return compare_trees(ref, out_dir)


def _regenerate_video(ref: Path, out_dir: str | os.PathLike) -> dict:
    """Regenerate a ``synth-scene --video`` folder from its ``video.json`` and compare."""
    from .video_files import write_video

    try:
        meta = json.loads((ref / "video.json").read_text(encoding="utf-8"))
        options = dict(
            seed=int(meta["seed"]),
            sequences=int(meta["sequences"]),
            n_frames=int(meta["frames"]),
            image_size=tuple(int(v) for v in meta["image_size"]),
            static=bool(meta["static"]),
            antialias=int(meta["antialias"]),
            image_noise=float(meta["image_noise_sigma"]),
        )
    except (KeyError, ValueError, TypeError, json.JSONDecodeError) as exc:
        raise FormatError(
            f"{ref}/video.json: missing or invalid generation parameters ({exc})"
        ) from exc
    write_video(out_dir, overwrite=True, **options)
    return compare_trees(ref, out_dir)
