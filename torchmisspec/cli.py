"""The ``torchmisspec`` command: ``torchmisspec demo`` (paper §5.1 end to end) and ``torchmisspec design``."""

from __future__ import annotations

import argparse
import sys

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from .experiments import linear_demo

    print(f"paper 5.1: {args.n_train} random experiments in [-1, 1]^2, T = 11 on [0, 6], oracle noise std "
          f"{args.noise_std}, seed {args.seed}")
    r = linear_demo(args.out, n_train=args.n_train, n_test=args.n_test, seed=args.seed, noise_std=args.noise_std,
                    progress=not args.quiet)
    print(f"fitted GP: lengthscale {r.lengthscale:.4g}, outputscale {r.outputscale:.4g}, noise variance "
          f"{r.noise_variance:.4g}, log marginal likelihood {r.log_marginal_likelihood:.6g} "
          f"({r.seconds['fit']:.2f} s)")
    print(f"integrated error of the correction over D: {r.integrated_error:.4g}   "
          f"(energy of F: {r.energy_of_F:.4g}, ratio {r.integrated_error / r.energy_of_F:.3f}; "
          f"energy of G + F: {r.energy_of_G_plus_F:.4g})")
    print(f"trajectory RMSE on {r.n_test} new initial conditions: corrected {r.rmse_corrected:.4g}, misspecified "
          f"{r.rmse_misspecified:.4g}, ratio {r.rmse_ratio:.3f} ({r.rhs_evaluations} right-hand-side evaluations, "
          f"{r.seconds['predict']:.2f} s)")
    if r.figures:
        print("figures: " + ", ".join(r.figures) + f"; numbers: {args.out}/results.json")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchmisspec", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run paper 5.1 end to end (fit, predict, figures)",
                          description="Paper 5.1 end to end: simulate random experiments of the linear system, fit "
                                      "the correction GP, predict new trajectories, write figures.")
    demo.add_argument("--out", default="demo-output", help="folder for the figures and results.json "
                                                           "(default: %(default)s)")
    demo.add_argument("--n-train", type=int, default=40, help="number of training experiments (default: 40)")
    demo.add_argument("--n-test", type=int, default=20, help="number of new initial conditions (default: 20)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    demo.add_argument("--noise-std", type=float, default=1e-2, help="std of the derivative noise (default: 1e-2)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    from ._errors import TorchMisspecError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except TorchMisspecError as exc:
        print(f"torchmisspec {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
