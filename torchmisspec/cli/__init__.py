"""The ``torchmisspec`` command: the scientist's loop on a lab's files.

``fit`` (learn the correction from a table of observed trajectories, calibrate its bands, save the model),
``calibrate`` (recalibrate a saved model's bands), ``predict`` (trajectories from new initial conditions with bands,
as a CSV and a figure), ``design`` (the next experiments), ``population`` (experiments that differ in some of G's
parameters: subjects, and the next subject's design) and ``demo`` (paper 5.1 end to end). Every command reads lab
tables with the same column options and takes the user's system as ``module:function`` or ``file.py:function``.
Every error is one line on stderr naming the fix, with exit status 2; no traceback reaches the user (set
``TORCHMISSPEC_TRACEBACK=1`` to see one when reporting a bug).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from functools import partial
from pathlib import Path

from .._errors import InputError
from ._common import seed
from ._design import add_design
from ._fit import add_calibrate, add_fit
from ._population import add_population
from ._predict import add_predict

__all__ = ["build_parser", "main"]


def _demo(args: argparse.Namespace) -> int:
    from ..paper.demo import linear_demo

    if not args.out.strip():
        raise InputError(f"--out: expected a folder name, got {args.out!r}")
    try:  # the folder is checked before the work, as every command's output
        Path(args.out).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: cannot write {args.out!r} (a folder that can be created): {exc.strerror}") from None

    print(
        f"paper 5.1: {args.n_train} random experiments in [-1, 1]^2, T = 11 on [0, 6], oracle noise std "
        f"{args.noise_std}, seed {args.seed}"
    )
    r = linear_demo(
        args.out,
        n_train=args.n_train,
        n_test=args.n_test,
        seed=args.seed,
        noise_std=args.noise_std,
        progress=not args.quiet,
    )
    print(
        f"fitted GP: lengthscale {r.lengthscale:.4g}, outputscale {r.outputscale:.4g}, noise variance "
        f"{r.noise_variance:.4g}, log marginal likelihood {r.log_marginal_likelihood:.6g} ({r.seconds['fit']:.2f} s)"
    )
    print(
        f"integrated error of the correction over D: {r.integrated_error:.4g}   "
        f"(energy of F: {r.energy_of_F:.4g}, ratio {r.integrated_error / r.energy_of_F:.3f}; "
        f"energy of G + F: {r.energy_of_G_plus_F:.4g})"
    )
    print(
        f"trajectory RMSE on {r.n_test} new initial conditions: corrected {r.rmse_corrected:.4g}, misspecified "
        f"{r.rmse_misspecified:.4g}, ratio {r.rmse_ratio:.3f} ({r.rhs_evaluations} right-hand-side evaluations, "
        f"{r.seconds['predict']:.2f} s)"
    )
    if r.figures:
        print("figures: " + ", ".join(r.figures) + f"; numbers: {args.out}/results.json")
    return 0


def _add_demo(sub) -> None:
    demo = sub.add_parser(
        "demo",
        help="run paper 5.1 end to end (fit, predict, figures)",
        description="Paper 5.1 end to end: simulate random experiments of the linear system, fit "
        "the correction GP, predict new trajectories, write figures.",
    )
    demo.add_argument(
        "--out", default="demo-output", help="folder for the figures and results.json (default: %(default)s)"
    )
    demo.add_argument("--n-train", type=int, default=40, help="number of training experiments (default: 40)")
    demo.add_argument("--n-test", type=int, default=20, help="number of new initial conditions (default: 20)")
    demo.add_argument("--seed", type=seed, default=0, help="random seed (default: 0)")
    demo.add_argument("--noise-std", type=float, default=1e-2, help="std of the derivative noise (default: 1e-2)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=_demo)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (it prints the usage first), exit status 2 as argparse's own."""

    def error(self, message: str):
        hint = ""
        if message.endswith("expected one argument"):  # a value that starts with '-' reads as an option
            option = message.split()[1].split("/")[-1].rstrip(":")
            given = [v for a, v in zip(_ARGV, _ARGV[1:], strict=False) if a == option and v.startswith("-")]
            value = given[0] if given else "VALUE"
            hint = f"; a value that starts with '-' is written {option}=VALUE: write {option}={value}"
        self.exit(2, f"{self.prog}: error: {_one_line(message)}{hint} (see '{self.prog} --help')\n")


_ARGV: list[str] = []  # the command line being parsed (named in the parser's messages)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="torchmisspec", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    add_fit(sub)
    add_calibrate(sub)
    add_predict(sub)
    add_design(sub)
    add_population(sub)
    _add_demo(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command; 0 on success, 2 on any error (one line on stderr)."""
    from .._errors import TorchMisspecError

    _ARGV[:] = sys.argv[1:] if argv is None else [str(a) for a in argv]
    try:
        parser = build_parser()
        args, unknown = parser.parse_known_args(argv)  # argparse's own errors: one line, SystemExit(2)
        if unknown:  # named by the command, as every other error
            parser.exit(
                2,
                f"torchmisspec {args.command}: error: unrecognized arguments: {' '.join(unknown)} (see "
                f"'torchmisspec {args.command} --help')\n",
            )
    except KeyboardInterrupt:
        print("torchmisspec: interrupted", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help (0) or a usage error (2, its line already printed)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        with warnings.catch_warnings():
            warnings.showwarning = partial(_warning_line, args.command, set())
            return args.func(args)
    except KeyboardInterrupt:
        print(f"torchmisspec {args.command}: interrupted; nothing more was written", file=sys.stderr)
        return 2
    except TorchMisspecError as exc:
        print(f"torchmisspec {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # the package never exits: the --system code did (at import, or in its function)
        print(
            f"torchmisspec {args.command}: error: --system: expected the system's code to return, got "
            f"SystemExit({exc.code!r}) (it calls exit() or sys.exit() when imported or run); remove that call, or put "
            "it under if __name__ == '__main__':",
            file=sys.stderr,
        )
        return 2
    except OSError as exc:  # a file that cannot be read or written
        print(f"torchmisspec {args.command}: error: {exc.strerror or exc} ({exc.filename or ''})", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: still one line, with what to send us
        if os.environ.get("TORCHMISSPEC_TRACEBACK"):
            raise
        print(
            f"torchmisspec {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} (please report it "
            "with the command; TORCHMISSPEC_TRACEBACK=1 shows the traceback)",
            file=sys.stderr,
        )
        return 2


def _one_line(exc: BaseException | str) -> str:
    """A message on one line, its advice in the command line's words (:data:`_FLAGS`)."""
    text = " ".join(str(exc).split())
    for keyword, flag in _FLAGS:
        text = text.replace(keyword, flag)
    return text


def _warning_line(command: str, seen: set, message, category, filename, lineno, file=None, line=None) -> None:
    """The library's warnings reach the user as one line each on stderr, without the source line, each text once
    (``seen``: the lines printed by this command; a population's fits can each give the same one)."""
    text = f"torchmisspec {command}: warning: {_one_line(message)}"
    if text not in seen:
        seen.add(text)
        print(text, file=sys.stderr)


#: Python keywords in the library's advice and the command line's flags for them.
_FLAGS = tuple((f"noise='{name}'", f"--noise {name}") for name in ("additive", "relative", "counts", "poisson")) + (
    ("estimator_error tells which is best", "--derivative names one: central, smooth or gp"),
    ("fit the correction through the ODE with tms.fit_trajectories", "refine it through the ODE with --refine"),
    ("refit with refine=True", "refit with --refine"),
)


if __name__ == "__main__":
    raise SystemExit(main())
