"""The body stage of a prepare: the multi-view body fit to the followed person's targets and masks (``fit``, the masks
as its silhouette term in ``masks``), the cameras it corrected, and each camera's distance checked on the masks
(``camera_depth``); ``bodies`` runs them."""
