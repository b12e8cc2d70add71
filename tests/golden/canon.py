"""Location-free digests of a command's outputs, so that a golden file made in one checkout
holds in any other: absolute paths inside text and Parquet files are replaced by placeholders
before hashing (``{ROOT}`` the checkout, ``{D}`` the derived inputs, ``{O}`` the output)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

TEXT = (".json", ".jsonl", ".txt", ".csv", ".md")


def _subst(text: str, subs: dict[str, str]) -> str:
    for old, new in sorted(subs.items(), key=lambda kv: -len(kv[0])):
        text = text.replace(old, new)
    return text


def canonical(path: Path, subs: dict[str, str]) -> bytes:
    if path.suffix in TEXT:
        return _subst(path.read_text(encoding="utf-8"), subs).encode()
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        rows = pq.read_table(path).to_pylist()
        text = json.dumps(rows, sort_keys=True, default=repr)
        return _subst(text, subs).encode()
    return path.read_bytes()


def digests(out: Path, subs: dict[str, str]) -> dict[str, str]:
    """sha256 of every file under ``out`` but the record folder, by relative path."""
    return {
        p.relative_to(out).as_posix(): hashlib.sha256(canonical(p, subs)).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.relative_to(out).parts
    }


def record(out: Path, subs: dict[str, str]) -> dict:
    """The folder's run record and, per frame, its recorded outputs and statistics."""
    rec = out / ".sparsetools"
    if not (rec / "run.json").is_file():
        return {}
    run = json.loads(_subst((rec / "run.json").read_text(), subs))
    frames = {}
    if (rec / "frames.jsonl").is_file():
        for line in (rec / "frames.jsonl").read_text().splitlines():
            d = json.loads(_subst(line, subs))
            frames[d["key"]] = {"outputs": d["outputs"], "stats": d["stats"]}
    return {"run": run, "frames": frames}
