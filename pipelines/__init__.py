"""Everything between files on disk and the model: readers and writers, the body model, calibration, the
synthetic data, the command-line tools, and the glue that opens a capture for fitting, evaluation and videos.

Sub-packages (imports flow one way, ``datasets`` first; ``tests/test_architecture.py`` keeps it so):

* ``datasets``: readers and writers of real formats (ZJU-MoCap, EasyMocap cameras, SMPL files, subjects);
* ``body``: the stand-in SMPL body and the SMPL glue that turns parameters into part transforms;
* ``calibration``: ChArUco detection, intrinsics, rig initialisation, bundle adjustment, reports;
* ``synthetic``: the synthetic capture in the real layouts (images, masks, SMPL fits, ChArUco shots, ``lbs/``);
* ``cli``: one module per console script and their shared plumbing;
* ``experiments``: the supplement's tables as experiments; it drives the real ``narf-fit`` (``cli.fit``) and the
  glue's evaluations, so it sits above the commands.

The top-level modules are the glue: ``fit_session`` (subject -> Trainer), ``autoencoder_session`` (THUman set ->
AutoencoderTrainer), ``rigid_session`` (rigid-object set -> Trainer, and its evaluation), ``evaluation``,
``autoencoder_evaluation``, ``video``, ``autoencoder_video`` and ``mesh_export``.
"""
