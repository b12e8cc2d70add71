"""Write ``tests/golden/train_v020.json``: what sparsetools 0.2.0 trained on a tiny dataset.

Run with the 0.2.0 code (``git worktree add /tmp/v020 aeafbc4``), from the checkout whose
golden file it makes (about 30 s on one core)::

    PYTHONPATH=/tmp/v020/src python tests/golden/train_make_v020.py

For every case of ``train_cases.py`` (supervised, supervised with the SFE LiDAR branch,
self-supervised at night with MCIE and SBM, self-supervised with the sparse SILog loss,
self-supervised with SFE branches in depth and pose) it records the fingerprint of a full
two-epoch run, of a run stopped by ``max_steps`` inside the second epoch, and of that run
resumed to the end. ``tests/test_train_golden.py`` checks that
today's code gives the same metrics (floats equal), checkpoints (tensors equal) and resume.

Bit identity holds on one kind of machine (torch's CPU kernels round differently from one CPU
to another): on a machine whose results differ from every ``train_v020*.json``, rename what
this writes to ``train_v020_<machine>.json`` and say in ``test_train_golden.py`` which machine.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(1, str(Path(__file__).resolve().parent))

from train_cases import CASES, dataset_digest, make_dataset, run_case


def same_but_best_config(a: dict, b: dict) -> bool:
    def strip(run):
        best = {k: v for k, v in run["checkpoints"]["best.pt"].items() if k != "config"}
        return {**run, "checkpoints": {**run["checkpoints"], "best.pt": best}}

    return strip(a) == strip(b)


def main() -> None:
    import torch

    import sparsetools

    golden = {
        "version": sparsetools.__version__,
        "torch": torch.__version__,
        "dataset": None,
        "cases": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        dataset = make_dataset(Path(tmp) / "ds")
        golden["dataset"] = dataset_digest(dataset)
        for name in CASES:
            golden["cases"][name] = case = run_case(name, dataset, Path(tmp))
            # 0.2.0 itself continues a stopped run exactly (a best.pt saved before the stop
            # keeps the configuration it was saved with: max_steps)
            assert same_but_best_config(case["resumed"], case["full"]), name
            print(name, case["full"]["metrics"][-1], flush=True)
    target = Path(__file__).with_name(f"train_v{golden['version'].replace('.', '')}.json")
    target.write_text(json.dumps(golden, indent=1, sort_keys=True) + "\n")
    print("wrote", target)


if __name__ == "__main__":
    main()
