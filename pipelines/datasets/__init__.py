"""Readers and writers of the file formats users bring, as the tools that write them lay them out
(``docs/formats.md``): ZJU-MoCap captures and their evaluation protocols (``zju_mocap``, ``capture``), EasyMocap
camera files (``easymocap``), SMPL model pickles (``smpl_files``) and subject names (``subjects``). Nothing here
imports the body model, calibration, the synthetic generator or the CLIs: real and synthetic data go through the
same readers.
"""
