"""The benchmarks behind BENCHMARKS.md, measured against peers in the same run (the scripts in ``scripts/`` are
their command lines). Built on the library, which never imports this subpackage.

* :mod:`~torchmisspec.benchmarks.reporting` - what every benchmark and study records and writes: the machine, the
  command line, median timings, JSON, and markdown blocks between markers in BENCHMARKS.md;
* :mod:`~torchmisspec.benchmarks.suite` - ``scripts/benchmark.py``: the families :mod:`~.fitting` (fit, gradient),
  :mod:`~.prediction`, :mod:`~.design` (design, naive), :mod:`~.contention` and :mod:`~.states` (realdata), the
  page written by :mod:`~.page`;
* :mod:`~.campaign`, :mod:`~.features`, :mod:`~.posterior` - ``scripts/benchmark_campaign.py``,
  ``benchmark_features.py`` and ``benchmark_posterior.py``, each a block of BENCHMARKS.md.
"""
