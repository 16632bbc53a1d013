"""Experiments that differ: per-experiment parameters of G with a population distribution, and a shared F.

Stages: the declaration (:mod:`~torchmisspec.population.model`, :mod:`~torchmisspec.population.distributions`),
the population's fit for a given correction (:mod:`~torchmisspec.population.nlme`: Laplace EM over every experiment's
conditional modes), the joint fit with F (:mod:`~torchmisspec.population.fit`), a new subject's prediction
(:mod:`~torchmisspec.population.predict`) and the design of its experiment (:mod:`~torchmisspec.population.design`).

Typical use::

    from torchmisspec.population import Population, fit_population, predict_subject, design_subject

    fit = fit_population(trajectories, system, Population(["ka", "ke", "V"]))
    print(fit.summary())
    new = predict_subject(fit, None, times, first=first_two_samples)  # new.posterior.interval(0.9)
    plan = design_subject(fit, candidate_times, 4, initial_states=[[4.0, 0.0]])  # plan.times
"""

from .design import Correction, SubjectDesign, SubjectParameters, design_subject
from .distributions import LogNormal, Normal
from .fit import PopulationFit, fit_population
from .model import Population
from .predict import SubjectPrediction, predict_subject

__all__ = [
    "Correction",
    "LogNormal",
    "Normal",
    "Population",
    "PopulationFit",
    "SubjectDesign",
    "SubjectParameters",
    "SubjectPrediction",
    "design_subject",
    "fit_population",
    "predict_subject",
]
