"""``dataset verify`` of the camera images a ``--store reference`` dataset keeps in place."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.dataset import ManifestRow, brief_error, bytes_sha256, reference_unchanged

__all__ = ["decode_rgb", "verify_reference"]


def decode_rgb(data: bytes, rel: str) -> np.ndarray:
    from ...io.image import decode_image_bytes

    img = decode_image_bytes(data, source=rel)
    if img.dtype != np.uint8:
        raise FormatError("not an 8-bit image")
    return img


def verify_reference(
    root: Path, r: ManifestRow, check_hashes: bool, roots: Mapping[str, Path]
) -> tuple[list[str], list[str], str]:
    """A referenced camera image: (problems, warnings, status), status ``ok``, ``missing``
    or ``changed``. Changed is the provenance record's rule (size, then modification time,
    then the hash of a small file: :func:`sparsetools.io.dataset.reference_unchanged`); with
    ``check_hashes`` a file whose bytes hash as recorded is only touched (a warning)."""
    from ...io.dataset_reader import resolve_rgb
    from ...io.provenance import HASH_LIMIT

    where = f"referenced image {r.rgb_path} (root '{r.rgb_root}')"
    try:
        path = resolve_rgb(root, r, roots)
        st = os.stat(path)
        data = path.read_bytes()
    except FormatError as exc:
        return [str(exc)], [], "missing"
    except OSError as exc:
        return [f"{r.id}: {where} cannot be read ({exc.strerror or exc})"], [], "missing"
    sha = bytes_sha256(data) if check_hashes or r.rgb_size <= HASH_LIMIT else None
    if not reference_unchanged(r, st, sha):
        if check_hashes and sha == r.rgb_sha256:
            return [], [f"{r.id}: {where} was touched (modification time differs) but holds "
                        "the bytes the build recorded"], "ok"  # fmt: skip
        what = (f"size {r.rgb_size} -> {st.st_size}" if st.st_size != r.rgb_size
                else "modification time" + (", sha256" if sha is not None else ""))  # fmt: skip
        return [f"{r.id}: {where} changed since the build ({what} differ); rebuild the "
                "sample (dataset build) or put the recorded file back"], [], "changed"  # fmt: skip
    if check_hashes and sha != r.rgb_sha256:
        return [f"{r.id}: {where} changed since the build (sha256 differs)"], [], "changed"
    problems = []
    try:
        img = decode_rgb(data, r.rgb_path)
        if img.shape[:2] != (r.height, r.width):
            problems.append(f"{r.id}: {where} is {img.shape[1]}x{img.shape[0]}, the manifest "
                            f"says {r.width}x{r.height}")  # fmt: skip
    except FormatError as exc:
        problems.append(f"{r.id}: {where} cannot be decoded ({brief_error(exc)})")
    return problems, [], "ok"
