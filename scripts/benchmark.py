#!/usr/bin/env python
"""Benchmarks of torchmisspec against peers measured in the same run (figures go into BENCHMARKS.md).

    python scripts/benchmark.py                 # every benchmark, full size
    python scripts/benchmark.py --only fit      # one of: fit, gradient, predict, design, naive (repeatable)
    python scripts/benchmark.py --smoke         # tiny sizes, checks the script runs (the test suite runs it)
    python scripts/benchmark.py --json out.json # also write the numbers as JSON
    python scripts/benchmark.py --threads 1     # torch threads (default: torch's own choice)

fit       N = 2,000 samples of paper 5.1's F (200 trajectories x 10 times, oracle noise std 1e-2), shared RBF kernel,
          all hyperparameters learned. Ours: CorrectionGP().fit. Peers: stock GPyTorch (ExactMarginalLogLikelihood
          + torch.optim.LBFGS, strong Wolfe, same modules, same start) with its default settings (CG / Lanczos above
          800 points) and with exact Cholesky (max_cholesky_size(10**5)); scikit-learn's GaussianProcessRegressor
          (ConstantKernel * RBF + WhiteKernel). Every likelihood is re-evaluated with our exact formula.
gradient  the analytic marginal-likelihood gradient (one factorization without a graph, weights Q, backward through
          the O(N^2) surrogate) vs autograd through torch.linalg.cholesky + cholesky_solve + logdet, one value +
          gradient at N = 500, 1000, 2000 (d_in = 2, d_out = 2, RBF); then a whole L-BFGS fit with either gradient.
predict   1,000 new initial conditions, 61 output times, GP trained on 440 samples (40 trajectories x 11):
          CorrectedODE.predict (cached solve, one kernel block per step) vs the same batched dopri5 solve with a
          right-hand side that calls the GPyTorch model at each step, (a) its full predictive distribution and
          (b) its fastest mean-only path (skip_posterior_variances + fast_pred_var, cached prediction strategy).
design    10,000 candidates, T = 20, K = 50, d = 2, RBF kernel: proxies + lazy greedy, wall time and peak memory.
naive     500 candidates, T = 11, K = 15: lazy greedy vs plain greedy vs the naive greedy of Algorithm 1 (fresh
          log-determinant per candidate per step), same picks required.
"""

from __future__ import annotations

import argparse
import json
import sys

import torch

from torchmisspec.benchmarks import suite


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--only", choices=list(suite.BENCHMARKS), action="append", help="run only these benchmarks (repeatable)"
    )
    parser.add_argument("--smoke", action="store_true", help="tiny sizes: check that the script runs")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (median reported)")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's choice)")
    parser.add_argument("--json", help="write the results to this JSON file")
    parser.add_argument("--markdown", help="write BENCHMARKS.md-style results here (needs every benchmark)")
    parser.add_argument("--design-worker", help=argparse.SUPPRESS)
    parser.add_argument("--contention-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    for name in ("design", "contention"):
        payload = getattr(args, f"{name}_worker")
        if payload:
            print(json.dumps(suite.WORKERS[name](*json.loads(payload))))
            return 0
    if args.markdown and args.only:
        parser.error("--markdown needs every benchmark; drop --only")
    repeats = args.repeats or (1 if args.smoke else 3)
    command = "python scripts/benchmark.py " + " ".join(argv if argv is not None else sys.argv[1:])
    results = suite.run(args.only or list(suite.BENCHMARKS), args.smoke, repeats, command)
    if args.json:
        suite.write_results(results, args.json)
    if args.markdown:
        suite.write_page(results, args.markdown)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
