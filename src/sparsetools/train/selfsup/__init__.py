"""Self-supervised depth from video (monodepth2, with EffisDepth's sparse loss and RNW's night
options; METHODS.md section 8).

- :mod:`.geometry`: back-projection, projection, axis-angle <-> matrix, pose vector -> 4x4, warp;
- :mod:`.photometric`: SSIM (3x3, reflection padding) and the photometric error pe;
- :mod:`.masks`: auto-mask and RNW's statistics-based mask (SBM);
- :mod:`.smoothness`: edge-aware smoothness of mean-normalised disparity;
- :mod:`.pose_net`: the pose network (two frames -> axis-angle + translation);
- :mod:`.data`: frame triplets (t-1, t, t+1) of a dataset's sequences;
- :mod:`.losses`: the loss of a batch (minimum reprojection, masks, smoothness, sparse loss);
- :mod:`.pbr`: RNW's priors-based regularization (PatchGAN discriminator, LSGAN losses) and
  :mod:`.pbr_reference`: its unpaired reference depths;
- :mod:`.task`: training (the task :func:`sparsetools.train.epochs.fit` drives, and its
  validation); :mod:`.pose_eval`: ATE over 5-frame snippets.

The depth network is the U-Net of :mod:`sparsetools.train.model` with ``output='disparity'``.
Run it with ``sparsetools train --self-supervised`` or
``train(TrainConfig(..., selfsup=SelfSupSettings(...)))``.
"""
