"""Where on the gravity set-up the kernels' errors come from: near the samples or far from them (issue 12).

For one realization of the kernel study (``scripts/study_kernels.py``: K random orbits, its seeds), each kernel's
squared error of F over the 81 x 81 grid of D is split by the distance from the grid point to the nearest sample:
near (< 0.2) and far (>= 0.5). Prints each kernel's evidence score, errors and the fraction of D that is far.

Usage::

    python scripts/probe_gravity_extrapolation.py --k 10 --realization 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import study_kernels  # noqa: E402 (the study whose realizations this probes)

import torchmisspec as tms  # noqa: E402
from torchmisspec import design  # noqa: E402
from torchmisspec.paper import _setup  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--k", type=int, default=10, help="number of orbits")
    parser.add_argument("--realization", type=int, default=2, help="realization index of the kernel study")
    args = parser.parse_args(argv)
    K, r = args.k, args.realization
    system, times = tms.systems.paper_gravity(), _setup.gravity_times()
    y0 = design.candidates.orbits(K, generator=torch.Generator().manual_seed(study_kernels.SEED + 100 * K + r))
    samples = tms.correction_samples(
        tms.simulate(system, y0, times),
        system,
        derivative="oracle",
        noise_std=_setup.NOISE_STD,
        generator=torch.Generator().manual_seed(study_kernels.SEED + 11 * r + K),
    )
    g = torch.linspace(-2, 2, 81, dtype=torch.float64)
    X = torch.cartesian_prod(g, g)
    truth = system.true_correction(X)
    distance = torch.cdist(X, samples.inputs).min(1).values
    near, far = distance < 0.2, distance >= 0.5
    print(f"K = {K}, realization {r}: {float(far.double().mean()):.2f} of D is >= 0.5 from every sample")
    for kernel in ("rbf", "matern52", "features", "features+rbf"):
        gp = tms.CorrectionGP(kernel=kernel, per_output=kernel == "features").fit(samples)
        with torch.no_grad():
            err = (gp.predict_mean(X) - truth).pow(2).sum(1)
        print(
            f"{kernel:13s} score {gp.evidence_score:9.1f}  mean squared error {float(err.mean()):.2e}  "
            f"near {float(err[near].mean()):.2e}  far {float(err[far].mean()):.2e}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
