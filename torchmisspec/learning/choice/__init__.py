"""Stage 2: the choice of F's model, scored on held-out experiments.

Candidates are scored by how well the corrected model predicts experiments it was not fitted on
(:mod:`.cross_validation`); one trajectory is cut into held-out time pieces (:mod:`._time_pieces`) and gets the
refined feature kernel as a rival (:mod:`._one_trajectory`); partly measured data choose between a correction learned
through the ODE and the known model alone (:mod:`._partial_choice`); the known model alone is kept where no candidate
beats it (:mod:`._do_no_harm`).
"""
