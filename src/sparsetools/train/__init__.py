"""Training and evaluation of depth networks: torch lives only here.

- :mod:`.config` (settings, resume rule, schedule), :mod:`.checkpoint` (run folders and
  checkpoints), :mod:`.runtime` (determinism, loaders, atomic files), :mod:`.plots` (curves and
  prediction pictures), :mod:`.evaluate` (metrics of checkpoints and depth files);
- :mod:`.loop` (:func:`~.loop.train`: settings, run folder, task) and :mod:`.epochs` (the
  epoch skeleton :func:`~.epochs.fit` behind the :class:`~.epochs.TrainingTask` protocol);
- supervised depth completion: :mod:`.data`, :mod:`.model`, :mod:`.losses`, :mod:`.supervised`;
- self-supervised training from video: :mod:`.selfsup`.
"""
