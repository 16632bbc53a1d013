"""Experimental design for the correction GP (paper §4): choose the initial conditions that teach the most about F.

The criterion is the information gain about F of noisy correction samples taken along the *proxy* trajectories,
those of the known model G alone from each candidate initial condition (Theorem 1 bounds the error of the proxy):

    f(S) = (d_out / 2) * logdet(I + K(P_S, P_S) / sigma^2)    nats (real-Gaussian convention)

with P_S the proxy points of the chosen set S restricted to the correction inputs and k the correction GP's kernel
(shared by the d_out outputs). The paper writes Gaussian entropies in the complex convention log((pi e)^k det), which
doubles every number; the designs are identical. f is monotone and submodular, so greedy maximisation is within
(1 - 1/e) of the optimum under a cardinality budget and within 1/2 under a partition matroid.

Public functions:

* :func:`proxy_trajectories` - known-model trajectories of all candidates (closed form for linear G).
* :func:`information_gain` - f of a set of sample points.
* :func:`variance_reduction` - the domain criterion (``greedy(..., criterion=DomainCriterion(...))``): the mean
  posterior variance of F over the domain D that a set of samples removes.
* :class:`ReadoutCriterion` - the criterion for experiments that read only combinations H y of the states (a
  :class:`~torchmisspec.Readout`): the information of the readings about F, linearised through the ODE
  (``greedy(..., criterion=ReadoutCriterion(readout))``; :func:`readout_sensitivity`,
  :func:`readout_information_gain`; the maths in :mod:`torchmisspec.design._readings`). Aimed at a box D of F's
  inputs with ``ReadoutCriterion(readout, domain=DomainCriterion(...))`` (:mod:`torchmisspec.design._readings_domain`).
  Where G has uncertain parameters, they are integrated out: the readings' information about F alone, theta's
  uncertainty (the fit's posterior, else the prior) acting as noise shared by the experiments
  (:mod:`torchmisspec.design._readings_theta`, which says why not the information about theta and F jointly). The
  criteria of correction samples evaluate G at theta's estimate (a plug-in). Systems with inputs: pass each
  candidate's input profile as ``controls``.
* :func:`greedy` - greedy / lazy greedy (identical picks) with optional partition-matroid capacities; its options
  grouped in small frozen objects: :class:`Partition` (at most so many picks per region), :class:`Proxy` (the
  trajectories the samples are predicted along), :class:`DomainCriterion` (aim at a box D of F's inputs) and
  :class:`Engine` (batches, screening, ties, the stochastic draw).
* :func:`refine` - a design's initial states moved by gradients of the criterion, beyond the candidate list.
* :func:`sampling_times` - which times to measure in given experiments under a per-experiment sample budget.
* :class:`Campaign` - the sequential loop: ``ask`` for experiments designed given the data so far, ``tell`` the
  measured trajectories (refit), ``history``, ``save`` / ``load``.
* :func:`random`, :func:`agnostic` - baseline designs (random; ignore G, i.e. constant proxy trajectories).
* :func:`marginal_gains` - gains of a given ordered design.
* :func:`true_information_gain`, :func:`proxy_gap_bound`, :func:`proxy_check` - the true criterion along the true
  trajectories and the Theorem 1 bound on the proxy's error.
"""

from . import candidates
from ._baselines import agnostic, marginal_gains, random
from ._campaign import Campaign
from ._common import DesignResult
from ._domain import CRITERIA, variance_reduction
from ._gain import ProxyCheck, information_gain, proxy_check, proxy_gap_bound, true_information_gain
from ._greedy import greedy
from ._options import DomainCriterion, Engine, Partition, Proxy
from ._proxy import proxy_trajectories
from ._readings import ReadoutCriterion, ReadoutSensitivity, readout_information_gain, readout_sensitivity
from ._refine import Refinement, refine
from ._times import SamplingTimes, sampling_times

__all__ = [
    "CRITERIA",
    "Campaign",
    "DesignResult",
    "DomainCriterion",
    "Engine",
    "Partition",
    "Proxy",
    "ProxyCheck",
    "ReadoutCriterion",
    "ReadoutSensitivity",
    "Refinement",
    "SamplingTimes",
    "agnostic",
    "candidates",
    "greedy",
    "information_gain",
    "marginal_gains",
    "proxy_check",
    "proxy_gap_bound",
    "proxy_trajectories",
    "random",
    "readout_information_gain",
    "readout_sensitivity",
    "refine",
    "sampling_times",
    "true_information_gain",
    "variance_reduction",
]
