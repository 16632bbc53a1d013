"""Stage: G's uncertain parameters theta, learned with F.

From the derivative samples in closed form (:mod:`.closed_form`: exact for a G linear in theta, Gauss-Newton with a
Laplace posterior otherwise), then refined through the ODE on the observed states (:mod:`.through_ode`).
"""
