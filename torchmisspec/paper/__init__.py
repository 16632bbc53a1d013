"""The paper's experiments, built on the library (the library never imports this subpackage).

Shulkind, Horesh and Avron, *Experimental Design for Non-Parametric Correction of Misspecified Dynamical Models*,
§5 ("Numerical Experiments"):

* :mod:`torchmisspec.paper.studies` - the error-vs-K studies of Fig 5 (:func:`~.studies.linear_study`) and Fig 8
  (:func:`~.studies.gravity_study`), returning a :class:`~.studies.StudyResult`.
* :mod:`torchmisspec.paper.figures` - the eight figures with the numbers behind them (:func:`~.figures.reproduce`,
  ``figure_1`` ... ``figure_8``; ``scripts/reproduce_paper.py`` is its command line), and the paper's priors.
* :mod:`torchmisspec.paper.demo` - §5.1 end to end (:func:`~.demo.linear_demo`), what ``torchmisspec demo`` runs.

The generic pieces these use live in the library: candidate sets in :mod:`torchmisspec.design.candidates`, figures in
:mod:`torchmisspec.plotting`, error measures in :mod:`torchmisspec.metrics`.
"""

from . import demo, figures, studies

__all__ = ["demo", "figures", "studies"]
