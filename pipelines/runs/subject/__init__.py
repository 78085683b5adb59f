"""The per-subject run kind: one avatar fitted to one capture in the ZJU-MoCap layout (``session``), its evaluation
on the protocol splits (``evaluation``), videos (``video``) and meshes (``mesh``)."""
