"""The layout stage of a prepare: the capture written in the ZJU-MoCap layout with its masks, overlays, splits and
report (``write``), the checks that flag a camera (``checks``) and each camera's colour measured on the floor
(``colour``)."""
