"""The embedded default: a synthetic capture written in exactly the real layouts, rendered from the stand-in body
(``capture``), its scene (cameras, motion, textures, light: ``scene``), the ChArUco calibration shots
(``charuco_shots``) and Animatable NeRF's ``lbs/`` folder (``lbs``). The generator never leaks into the model
or the fitting code: its output is read back through ``pipelines.datasets``.
"""
