"""Everything between files on disk and the model: readers and writers, the body model, calibration, the
synthetic data, the run kinds, the experiments and the command-line tools.

Sub-packages (imports flow one way, ``datasets`` first; ``tests/test_architecture.py`` keeps it so and checks that
the import graph has no cycle):

* ``datasets``: readers and writers of real formats (ZJU-MoCap, EasyMocap cameras, COLMAP, SMPL files, subjects);
* ``body``: the stand-in SMPL body and the SMPL glue that turns parameters into part transforms;
* ``calibration``: ChArUco detection, intrinsics, rig initialisation, bundle adjustment, reports;
* ``prepare``: real recordings in (``narf-prepare-capture``): keypoints, triangulation, body fit, masks, checks;
* ``synthetic``: the synthetic data in the real layouts (captures, ChArUco shots, THUman, SURREAL, rigid object);
* ``runs``: the run kinds (``subject``, ``autoencoder``, ``rigid``: start or resume, evaluate, render, export), one
  table of them (``runs.kinds``) and ``runs.fit``, the fit that ``narf-fit`` and ``narf-experiments`` call;
* ``viewer``: ``narf-view``, on ``runs``;
* ``experiments``: the supplement's tables as experiments, on ``runs``;
* ``cli``: one module per console script, turning flags into ``runs`` requests.
"""
