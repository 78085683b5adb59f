"""The cameras-in-step stage of a prepare: each camera's time offset estimated from the keypoints (``keypoints``) and
from the silhouettes (``silhouettes``), and the whole-frame shifts applied with the record the report keeps
(``apply``)."""
