"""Training and evaluation of depth networks: torch lives only here.

- :mod:`.config` (settings, resume rule, schedule), :mod:`.checkpoint` (run folders and
  checkpoints), :mod:`.runtime` (determinism, loaders, atomic files), :mod:`.plots` (curves and
  prediction pictures), :mod:`.evaluate` (metrics of checkpoints and depth files);
- supervised depth completion: :mod:`.data`, :mod:`.model`, :mod:`.losses`, :mod:`.loop`;
- self-supervised training from video: :mod:`.selfsup`.
"""
