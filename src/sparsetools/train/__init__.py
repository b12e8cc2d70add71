"""Training and evaluation of depth-completion baselines: torch lives only here."""
