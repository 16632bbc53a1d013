"""Experiments that differ: per-experiment parameters of G with a population distribution, and a shared F.

Stages: the declaration (:mod:`~torchmisspec.population.model`, :mod:`~torchmisspec.population.distributions`),
the population's fit for a given correction (:mod:`~torchmisspec.population.nlme`: Laplace EM over every experiment's
conditional modes), the joint fit with F (:mod:`~torchmisspec.population.fit`), a new subject's prediction
(:mod:`~torchmisspec.population.predict`) and the design of its experiment (:mod:`~torchmisspec.population.design`).
"""

from .distributions import LogNormal, Normal
from .model import Population

__all__ = ["LogNormal", "Normal", "Population"]
