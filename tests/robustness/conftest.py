"""Hardening suite (tests/robustness): bad-input corpus, fault injection, fuzzing.

The helper modules sit beside the tests (no package): ``corpus_builder`` writes the inputs,
``corpus_cases`` is the table of (command, bad input) cases, ``cli_helpers`` runs the
command line in-process and judges its output. See docs/reliability.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
