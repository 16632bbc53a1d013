"""Prediction: the corrected model integrated with torchdiffeq, its uncertainty bands, and their calibration.

:class:`~torchmisspec.CorrectedODE` (:mod:`.dynamics`) integrates dy/dt = G(y) + E[F(y) | data] and draws of F
(:mod:`._draws`); the bands are order statistics of the draws (:mod:`._bands`), calibrated on held-out experiments
(:mod:`.calibration`). The solver's settings of its solves are one option object, :class:`~torchmisspec.Solver`
(:mod:`.solver`).
"""
