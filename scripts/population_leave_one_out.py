"""Leave one subject out on a packaged population data set: the package's population fit against the classical
answer (the same population with F = 0), each held-out subject predicted from its first 2 measurements.

Usage::

    python scripts/population_leave_one_out.py orange K 0,1,2,3,4
    python scripts/population_leave_one_out.py loblolly A 0,3,6,9,12
    python scripts/population_leave_one_out.py chickweight r,K 0

Prints, per fold, whether F was kept, the log-RMSE of the subject's remaining measurements for both, and the fit's
seconds.
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import torch

import torchmisspec as tms
from torchmisspec import datasets
from torchmisspec.population import Population
from torchmisspec.population.fit import fit_population
from torchmisspec.population.predict import predict_subject


def _errors(fit, t, y, first) -> list[float]:
    out = []
    for model in (fit, fit.as_classical()):
        path = predict_subject(model, None, t, first=first, num_samples=8).posterior.mean_path[0, :, 0]
        ok = bool(torch.isfinite(path).all() and (path > 0).all())
        out.append(float((path[2:].log() - y[2:, 0].log()).pow(2).mean().sqrt()) if ok else math.inf)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset", help="a packaged data set (torchmisspec.datasets)")
    parser.add_argument("vary", help="the varying parameters, comma-separated")
    parser.add_argument("folds", help="the subjects left out (0-based), comma-separated")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    data = datasets.load(args.dataset)
    trajectories, system = data.trajectories, data.system
    for k in (int(x) for x in args.folds.split(",")):
        train = trajectories[[i for i in range(trajectories.num_experiments) if i != k]]
        t, y = trajectories[[k]].experiments()[0]
        start = time.perf_counter()
        fit = fit_population(train, system, Population(args.vary.split(",")), noise=data.noise, progress=False)
        seconds = time.perf_counter() - start
        first = tms.Trajectories(t[:2], y[:2][None], state_names=trajectories.state_names)
        package, classical = _errors(fit, t, y, first)
        print(
            f"{args.dataset} subject {k}: F kept {not fit.known_model}; log-RMSE package {package:.4f}, classical "
            f"{classical:.4f} (ratio {package / classical:.3f}); fit {seconds:.0f} s"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
