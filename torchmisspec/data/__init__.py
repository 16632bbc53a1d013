"""Trajectories: observed or simulated states of K experiments, and :func:`simulate`.

``Trajectories(times, states)`` holds ``states (K, T, d)`` sampled at ``times (T,)`` shared by all experiments or
``(K, T)`` one grid per experiment (irregular spacing allowed, strictly increasing along each row), or experiments
of different lengths given as lists of per-experiment arrays (ragged data). It wraps user
data as well as simulations and saves to / loads from ``.npz`` and text tables (``.csv``, ``.tsv``, ``.txt``) with
any column names. Missing entries (an empty cell, or NaN in arrays) are kept as NaN with a mask,
:attr:`Trajectories.observed`; infinite values are refused.

The code is split by concept into private modules: the :class:`Trajectories` container in ``_trajectories``, the
checks of what it is given in ``_input``, the file formats of :meth:`Trajectories.save` / :meth:`Trajectories.load`
in ``_tables`` (text tables) and ``_npz`` (archives), the :class:`Readout` in ``_readout``, and :func:`simulate` in
``_simulate``; the per-experiment covariates of a table in ``_covariates``.
"""

from ._covariates import experiment_labels, read_covariates
from ._readout import Readout
from ._simulate import simulate, simulate_known_each
from ._trajectories import Trajectories

__all__ = ["Readout", "Trajectories", "experiment_labels", "read_covariates", "simulate", "simulate_known_each"]
