"""``narf-view``: a browser viewer of a fitted avatar (viser), posable by frame, motion, hand and bone length."""
