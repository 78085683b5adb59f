"""The people stage of a prepare: which views show the same person (``multiview``: consensus and triangulation),
every person linked into tracks and whom to follow (``tracks``, ``targets``), the views that missed that person
looked at again (``crops``), the views where other people overlap left out (``occlusion``); ``follow`` runs them."""
