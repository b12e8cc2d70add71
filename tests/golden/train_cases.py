"""Tiny training runs whose results sparsetools 0.2.0 recorded in ``train_v020.json``.

Each case is one training configuration run three ways on one tiny video dataset (four
sequences of five 32x48 frames rendered by ``tests/test_selfsup_scene.py``: three for training,
one for validation, with ground truth and a sparse "LiDAR" of every third row):

- ``full``: two epochs;
- ``cut``: the same, stopped by ``max_steps`` inside the second epoch;
- ``resumed``: the cut run continued with ``resume=True`` to the end of the second epoch.

:func:`fingerprint` reduces a run folder to what must not change between versions: the
``metrics.csv`` rows as written (timing columns left out), ``config.json`` (paths left out),
a sha256 per entry of ``last.pt`` and ``best.pt`` (every tensor's dtype, shape and bytes:
weights, optimizer moments, RNG state; the training state without its timing) and the sha256
of ``curves.png`` and the prediction pictures. :func:`dataset_digest` fingerprints the input,
so a mismatch says whether the data or the training changed.

``train_make_v020.py`` writes the golden file with the 0.2.0 code; ``tests/test_train_golden.py``
checks that today's code gives the same.
"""

from __future__ import annotations

import csv
import hashlib
import json
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent.parent
if str(TESTS) not in sys.path:
    sys.path.insert(1, str(TESTS))

#: Columns of metrics.csv (and keys of a checkpoint's state) that measure time, not results.
TIMING = {"seconds", "samples_per_s", "epoch_seconds"}

#: Settings shared by every case (TrainConfig fields).
BASE = dict(width=4, epochs=2, batch_size=4, lr=2e-3, threads=1, pictures=1, seed=3)

#: Settings that did not exist in 0.2.0, pinned to what 0.2.0 did (0.4 changed their
#: defaults: the metric pose translation scale, the SFE levels, GT-free model selection).
LEGACY_SELFSUP = dict(pose_translation_scale=0.01, select_by="gt")
LEGACY_LIDAR = dict(lidar_scales=(1, 2, 4, 8, 16))
#: Keys (config, model_config, metrics rows) and metrics columns new since 0.2.0: left out of
#: the fingerprints (the pinned values are checked on their own by test_train_golden.py).
NEW_SINCE_020 = {
    "lidar_scales",
    "pose_translation_scale",
    "pose_failure_ratio",
    "lidar_dropout",
    "lidar_holdout",
    "select_by",
    "pbr",
    "pbr_coordinates",
    "pbr_weight",
    "pbr_discriminator_weight",
    "url",
    "densifier",
    "gate_alpha",
    "gate_beta",
    "ate",
    "ate_unscaled",
    "ate_still",
}

#: name -> TrainConfig fields (``selfsup``: SelfSupSettings fields) and the step the cut run
#: stops at (inside the second epoch: 15 training frames = 4 batches of 4, 4, 4, 3; 9 triplets
#: = 3 batches of 4, 4, 1).
CASES = {
    "supervised": dict(
        config=dict(input_mode="rgbd", loss="berhu", lr_schedule="step", lr_step=1),
        cut=6,
    ),
    "supervised_sfe": dict(
        config=dict(input_mode="rgb", lidar_encoder="sfe", **LEGACY_LIDAR), cut=5
    ),
    "selfsup_night": dict(
        config=dict(
            input_mode="rgb", selfsup=dict(pose_width=4, mcie=True, sbm=True, **LEGACY_SELFSUP)
        ),
        cut=4,
    ),
    "selfsup_sparse": dict(
        config=dict(
            input_mode="rgbd",
            lr_schedule="cosine",
            selfsup=dict(pose_width=4, sparse_loss="silog", sbm=True, scales=3, **LEGACY_SELFSUP),
        ),
        cut=5,
    ),
    "selfsup_sfe": dict(
        config=dict(
            input_mode="rgb",
            lidar_encoder="sfe",
            **LEGACY_LIDAR,
            selfsup=dict(
                pose_width=4,
                sparse_loss="l1",
                pose_lidar_encoder="sfe",
                auto_mask=False,
                **LEGACY_SELFSUP,
            ),
        ),
        cut=4,
    ),
}


def make_dataset(root: Path) -> Path:
    """The tiny video dataset every case trains on (written by the tests' own helpers)."""
    from test_selfsup_scene import video, write_video_dataset

    seqs = {
        f"s{i}": video(5, 32, 48, speed=0.5 + 0.15 * i, yaw_rate=0.01 * (i - 2), start=2.0 * i)
        for i in range(4)
    }
    splits = {"s0": "train", "s1": "train", "s2": "train", "s3": "val"}
    return write_video_dataset(root, seqs, splits)


def dataset_digest(root: Path) -> str:
    """sha256 of the dataset: every file's bytes, the manifest as rows (not Parquet bytes)."""
    import pyarrow.parquet as pq

    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        h.update(p.relative_to(root).as_posix().encode())
        if p.suffix == ".parquet":
            h.update(json.dumps(pq.read_table(p).to_pylist(), sort_keys=True).encode())
        else:
            h.update(p.read_bytes())
    return h.hexdigest()


def make_config(name: str, dataset: Path, out: Path, **kw):
    """The TrainConfig of case ``name`` (``kw`` overrides fields)."""
    from sparsetools.train.config import SelfSupSettings, TrainConfig

    fields = {**BASE, **CASES[name]["config"], **kw}
    if fields.get("selfsup") is not None:
        fields["selfsup"] = SelfSupSettings(**fields["selfsup"])
    return TrainConfig(dataset=str(dataset), out_dir=str(out), **fields)


def _canonical(obj):
    """JSON-able form of a checkpoint entry: tensors as digests of dtype, shape and bytes."""
    import torch

    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        raw = t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b""
        return f"tensor:{t.dtype}:{tuple(t.shape)}:{hashlib.sha256(raw).hexdigest()}"
    if isinstance(obj, dict):
        return {str(k): _canonical(v) for k, v in obj.items() if k not in TIMING}
    if isinstance(obj, list | tuple):
        return [_canonical(v) for v in obj]
    if isinstance(obj, float):
        return repr(obj)  # exact, and NaN/inf survive JSON
    return obj


def without_new_keys(obj):
    """``obj`` with the dictionary keys of :data:`NEW_SINCE_020` removed, at every depth."""
    if isinstance(obj, dict):
        return {k: without_new_keys(v) for k, v in obj.items() if k not in NEW_SINCE_020}
    if isinstance(obj, (list, tuple)):
        return type(obj)(without_new_keys(v) for v in obj)
    return obj


def checkpoint_digests(path: Path) -> dict[str, str]:
    """sha256 per top-level entry of a checkpoint (run paths and timing left out)."""
    import torch

    raw = torch.load(path, map_location="cpu", weights_only=True)
    out = {}
    for key, value in sorted(raw.items()):
        if key in TIMING:
            continue
        if key == "config":
            value = {k: v for k, v in value.items() if k not in ("dataset", "out_dir")}
        text = json.dumps(_canonical(without_new_keys(value)), sort_keys=True)
        out[key] = hashlib.sha256(text.encode()).hexdigest()
    return out


def fingerprint(run: Path, summary) -> dict:
    """What a finished (or stopped) run must reproduce exactly."""
    with open(run / "metrics.csv", newline="") as f:
        rows = [
            {k: v for k, v in r.items() if k not in TIMING | NEW_SINCE_020}
            for r in csv.DictReader(f)
        ]
    config = json.loads((run / "config.json").read_text())
    pictures = {
        p.relative_to(run).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted([run / "curves.png", *(run / "predictions").glob("*.png")])
    }
    return {
        "metrics": rows,
        "summary": {
            "epochs_done": summary.epochs_done,
            "steps": summary.steps,
            "best_epoch": summary.best_epoch,
            "best_metric": summary.best_metric,
            "best_value": repr(summary.best_value),
            "self_supervised": summary.self_supervised,
        },
        "config": without_new_keys(
            {k: v for k, v in config.items() if k not in ("dataset", "out_dir")}
        ),
        "new_settings": {
            k: config.get(k, (config.get("selfsup") or {}).get(k)) for k in sorted(NEW_SINCE_020)
        },
        "checkpoints": {name: checkpoint_digests(run / name) for name in ("last.pt", "best.pt")},
        "pictures": pictures,
    }


def run_case(name: str, dataset: Path, tmp: Path) -> dict:
    """The case's full, cut and resumed runs (in folders under ``tmp``), fingerprinted."""
    from sparsetools.train.loop import train

    out = {}
    full = train(make_config(name, dataset, tmp / f"{name}_full"))
    out["full"] = fingerprint(tmp / f"{name}_full", full)
    cut_dir = tmp / f"{name}_cut"
    cut = train(make_config(name, dataset, cut_dir, max_steps=CASES[name]["cut"]))
    out["cut"] = fingerprint(cut_dir, cut)
    resumed = train(make_config(name, dataset, cut_dir), resume=True)
    out["resumed"] = fingerprint(cut_dir, resumed)
    return out
