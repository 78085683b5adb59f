"""The body model: the generated SMPL-format stand-in (``standin``), the choice between a user's SMPL file and the
stand-in (``locate``), and the SMPL glue that poses a body with smplx and turns it into the per-part transforms,
bone lengths and pose features the model consumes (``model``; the maths lives in ``narf.kinematics``).
"""
