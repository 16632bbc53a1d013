"""Stage 1: samples of the missing term F from observed trajectories.

F is never observed directly: its samples are estimated derivatives minus G at the observed states
(:mod:`.observations`), by a stencil (:mod:`._stencils`), a GP in time (:mod:`._gp_in_time`), chosen by a
self-check on the data (:mod:`._estimators`).
"""
