"""Stage 3: the chosen model refined through the ODE on the observed states.

:mod:`.trajectory_fit` matches the measurements themselves (no derivative estimates), by the MAP of pseudo-targets
and state offsets (:mod:`._trajectory_map`, its Levenberg-Marquardt steps :mod:`._levenberg_marquardt`, its Jacobians
:mod:`._jacobian`, what it does when a solve fails :mod:`._fit_fallbacks`); a sparse rival prices each term through
the ODE (:mod:`._term_price`). Partly measured states and the initial states that were not measured: :mod:`.partial`,
:mod:`._first_model`. The classical answer, the known model alone fitted through the ODE: :mod:`._known_fit`.
"""
