"""The ``torchmisspec`` command: ``torchmisspec demo`` (paper §5.1 end to end), ``torchmisspec fit`` (learn the
correction from observed trajectories) and ``torchmisspec design``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from .paper.demo import linear_demo

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
        f"{r.noise_variance:.4g}, log marginal likelihood {r.log_marginal_likelihood:.6g} "
        f"({r.seconds['fit']:.2f} s)"
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


def _read_table(path: str, what: str):
    """A numeric array from .npz (array ``what`` or the only one), .npy, or CSV/TXT (an optional header row).

    Nothing is unpickled; unreadable, non-UTF-8 or non-numeric files raise :class:`InputError`.
    """
    import zipfile

    import numpy as np

    from ._errors import InputError

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what}: file {path!r} does not exist")
    if p.suffix not in (".csv", ".txt", ".npz", ".npy"):
        raise InputError(f"{what}: expected a .csv, .txt, .npz or .npy file, got {path!r}")
    try:
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as data:
                if what in data.files:
                    arr = data[what]
                elif len(data.files) == 1:
                    arr = data[data.files[0]]
                else:
                    raise InputError(f"{path}: expected an array named {what!r} (or a single array), got {data.files}")
        elif p.suffix == ".npy":
            arr = np.load(p, allow_pickle=False)
        else:
            lines = [ln for ln in p.read_text(encoding="utf-8").splitlines() if ln.strip()]
            if lines:
                try:
                    float(lines[0].replace(",", " ").split()[0])
                except ValueError:
                    lines = lines[1:]  # a header row
            arr = np.array([[float(v) for v in ln.replace(",", " ").split()] for ln in lines], dtype=np.float64)
    except InputError:
        raise
    except (ValueError, OSError, EOFError, UnicodeDecodeError, zipfile.BadZipFile) as exc:
        raise InputError(
            f"{what}: expected a numeric table in {path!r} (UTF-8 text, or .npy/.npz without pickled objects), but it "
            f"could not be read ({type(exc).__name__}: {str(exc)[:160]})"
        ) from exc
    if arr.dtype.kind not in "iuf" or arr.size == 0:
        raise InputError(
            f"{what}: expected a non-empty array of real numbers in {path!r}, got dtype {arr.dtype}, shape {arr.shape}"
        )
    return arr


def _parse_times(text: str):
    """``start:stop:count`` (equally spaced) or a comma list of times."""
    import torch

    from ._errors import InputError

    message = f"--times: expected 'start:stop:count' with count >= 1 or a comma list of numbers, got {text!r}"
    try:
        if ":" in text:
            start, stop, count = text.split(":")
            count = int(count)
            if count < 1:
                raise InputError(message)
            return torch.linspace(float(start), float(stop), count, dtype=torch.float64)
        return torch.tensor([float(v) for v in text.split(",")], dtype=torch.float64)
    except ValueError as exc:
        raise InputError(message) from exc


def _gp_from_args(args: argparse.Namespace, **override):
    """The CorrectionGP the --kernel, --lengthscale, --outputscale, --noise-variance and --degree options describe."""
    from .gp import CorrectionGP

    return CorrectionGP(
        kernel=args.kernel,
        lengthscale=override.get("lengthscale", args.lengthscale),
        outputscale=args.outputscale,
        noise_variance=args.noise_variance,
        degree=args.degree,
    )


def _check_output(path: str, suffixes: tuple[str, ...]) -> Path:
    """The output file: a known suffix, in a folder that exists and is writable (checked before any work)."""
    import os

    from ._errors import InputError

    out = Path(path)
    if out.suffix not in suffixes:
        raise InputError(f"--out: expected a {' or '.join(suffixes)} file name, got {path!r}")
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir() or not os.access(folder, os.W_OK) or (out.exists() and not os.access(out, os.W_OK)):
        raise InputError(f"--out: cannot write {path!r} (the folder must exist and be writable)")
    return out


def _design(args: argparse.Namespace) -> int:
    import json

    import torch

    from . import design
    from ._errors import InputError
    from .systems import load_system

    out = _check_output(args.out, (".csv", ".json"))
    system = load_system(args.system)
    candidates = torch.as_tensor(_read_table(args.candidates, "candidates"), dtype=torch.float64)
    if candidates.dim() == 1:
        candidates = candidates.unsqueeze(-1)
    times = _parse_times(args.times)
    gp = _gp_from_args(args)
    partition = capacities = None
    if args.partition is not None:
        labels = torch.as_tensor(_read_table(args.partition, "partition")).reshape(-1)
        if labels.is_floating_point() and not bool((labels == labels.round()).all()):
            raise InputError(f"--partition: expected integer region labels, got fractional values in {args.partition}")
        partition = labels.long()
        if args.capacities is None:
            raise InputError("--capacities: expected the most picks per region with --partition, got none")
    if args.capacities is not None:
        try:
            if "=" in args.capacities:
                capacities = {int(k): int(v) for k, v in (kv.split("=") for kv in args.capacities.split(","))}
            else:
                capacities = [int(v) for v in args.capacities.split(",")]
        except ValueError as exc:
            raise InputError(
                f"--capacities: expected 'label=count,...' or 'count,count,...', got {args.capacities!r}"
            ) from exc
    conditioned = 0
    if args.data is not None:  # condition the design on the experiments already run
        from .data import Trajectories
        from .gp import CorrectionGP
        from .observations import correction_samples

        samples = correction_samples(Trajectories.load(args.data), system, derivative=args.derivative)
        shared = samples.with_shared_noise()  # the design conditions one kernel shared by the outputs
        if shared is not samples:
            samples = shared
            from ._errors import TorchMisspecWarning, warn

            warn(
                "design: the derivative estimator's noise differs between the outputs; each sample is counted as "
                "noisy as its noisiest output, since the design conditions one kernel shared by the outputs",
                TorchMisspecWarning,
            )
        if args.learn_hyperparameters:
            gp = CorrectionGP(kernel=args.kernel, degree=args.degree).fit(samples)
        else:
            gp = gp.fit(samples)
        conditioned = len(samples)
    elif args.learn_hyperparameters:
        raise InputError("--learn-hyperparameters: learning needs data; pass --data observed.csv")
    if args.criterion != "information" and args.method not in ("lazy", "plain", "naive", "greedy"):
        raise InputError(f"--criterion {args.criterion}: only the greedy methods use it, got --method {args.method}")
    common = dict(system=system, times=times, gp=gp, progress=not args.quiet)
    if args.method == "random":
        plan = design.random(
            candidates,
            args.budget,
            generator=torch.Generator().manual_seed(args.seed),
            partition=partition,
            capacities=capacities,
            **common,
        )
    elif args.method == "agnostic":
        plan = design.agnostic(candidates, args.budget, partition=partition, capacities=capacities, **common)
    else:
        method = "plain" if args.method == "greedy" else args.method
        plan = design.greedy(
            candidates,
            args.budget,
            method=method,
            partition=partition,
            capacities=capacities,
            criterion=args.criterion,
            proxy=args.proxy,
            **common,
        )
    units = "mean variance of F over D removed" if args.criterion == "domain" else "nats (real-Gaussian convention)"
    rows = [
        {"order": i, "index": int(c), "gain": float(g), **{f"y{j}": float(v) for j, v in enumerate(pt)}}
        for i, (c, g, pt) in enumerate(
            zip(plan.indices.tolist(), plan.gains.tolist(), plan.points.tolist(), strict=True)
        )
    ]
    if out.suffix == ".json":
        out.write_text(
            json.dumps(
                {
                    "system": system.name,
                    "method": plan.method,
                    "budget": args.budget,
                    "indices": plan.indices.tolist(),
                    "gains": plan.gains.tolist(),
                    "information_gain": plan.information_gain,
                    "points": plan.points.tolist(),
                    "criterion": args.criterion,
                    "conditioned_on_samples": conditioned,
                    "proxy": plan.diagnostics.get("proxy"),
                    "units": units,
                },
                indent=2,
            )
        )
    else:  # .csv (the suffix was checked before the work)
        import csv

        with out.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    print(
        f"{plan.method} design of {len(plan)} experiments from {candidates.shape[0]} candidates on "
        f"{system.name}"
        + (f", conditioned on {conditioned} samples of {args.data}" if conditioned else "")
        + f": criterion {args.criterion} {plan.information_gain:.4g} ({units}); indices {plan.indices.tolist()}; "
        f"written to {out}"
    )
    return 0


def _fit(args: argparse.Namespace) -> int:
    from ._errors import InputError
    from .data import Trajectories
    from .learning import fit_correction
    from .systems import load_system

    out = _check_output(args.out, (".pt",))
    state_columns = None
    if args.state_columns is not None:
        state_columns = [c.strip() for c in args.state_columns.split(",")]
        if not all(state_columns):
            raise InputError(f"--state-columns: expected comma separated column names, got {args.state_columns!r}")
    experiment_column = args.experiment_column or None  # '' = no experiment column: one experiment
    lengthscale = args.lengthscale.strip().lower()
    if lengthscale not in ("cv", "ml"):
        try:
            lengthscale = float(lengthscale)
        except ValueError:
            raise InputError(f"--lengthscale: expected cv, ml or a positive number, got {args.lengthscale!r}") from None
    fixed = any(v is not None for v in (args.outputscale, args.noise_variance))
    if args.kernel == "auto" and (fixed or args.lengthscale.strip().lower() != "cv"):
        args.kernel = "rbf"  # fixed hyperparameters or a lengthscale not cross-validated: the RBF kernel, as before
    template = None if args.kernel == "auto" else _gp_from_args(args, lengthscale=None)
    system = load_system(args.system)
    trajs = Trajectories.load(
        args.data, time_column=args.time_column, experiment_column=experiment_column, state_columns=state_columns
    )
    if template is not None and template.kernel in ("polynomial", "features") and isinstance(lengthscale, float):
        raise InputError(
            f"--lengthscale: the {template.kernel} kernel has no lengthscale, got {args.lengthscale!r}; pass cv or ml"
        )
    gp = fit_correction(
        trajs, system, gp=template, derivative=args.derivative, lengthscale=lengthscale, refine=args.refine or None
    )
    samples = gp.samples_
    gp.save(out)

    def show(value) -> str:
        return "-" if value is None else (f"{value:.4g}" if isinstance(value, float) else str(value.tolist()))

    scale = "" if gp.lengthscale is None else f"lengthscale {show(gp.lengthscale)}, "
    times = f"{min(trajs.lengths)}-{max(trajs.lengths)}" if trajs.is_ragged else str(trajs.num_times)
    print(
        f"fitted {gp.kernel} correction GP of '{system.name}' on N = {len(samples)} samples ({trajs.num_experiments} "
        f"experiments x {times} times, derivative {args.derivative!r}): {scale}outputscale "
        f"{show(gp.outputscale)}, noise variance {show(gp.noise_variance)}, log marginal likelihood "
        f"{gp.log_marginal_likelihood_:.6g}; written to {out}"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="torchmisspec", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
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
    demo.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    demo.add_argument("--noise-std", type=float, default=1e-2, help="std of the derivative noise (default: 1e-2)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    demo.set_defaults(func=_demo)

    fit = sub.add_parser(
        "fit",
        help="learn the correction F from observed trajectories and save the model",
        description="Learn the missing term F of dy/dt = G(y) + F(y) from observed trajectories: estimate dy/dt from "
        "the states, form the correction samples dy/dt - G(y), fit the correction GP (lengthscale by "
        "cross-validation on held-out experiments, the rest by marginal likelihood; torchmisspec.fit_correction) "
        "and save it (read it back with torchmisspec.CorrectionGP.load).",
    )
    fit.add_argument(
        "--data",
        required=True,
        help="observed trajectories: a .csv, .tsv or .txt table with a header row (one row per experiment and "
        "time, rows in any order) or an .npz written by Trajectories.save",
    )
    fit.add_argument(
        "--system",
        required=True,
        help="the known model: a built-in name (paper_linear, paper_gravity) or 'module:function' / "
        "'path/to/file.py:function', a function returning a torchmisspec.MisspecifiedSystem (its code is run)",
    )
    fit.add_argument("--time-column", default="time", help="name of the time column (default: %(default)s)")
    fit.add_argument(
        "--experiment-column",
        default="experiment",
        help="name of the column labelling the experiments (default: %(default)s; when the file has no such column, "
        "or with '', all rows are one experiment)",
    )
    fit.add_argument(
        "--state-columns", help="comma separated state column names, in order (default: every other column)"
    )
    fit.add_argument(
        "--derivative",
        default="auto",
        help="how dy/dt is estimated from the states: auto (default: the estimator whose self-check on the known "
        "model is best), central, smooth, gp (a Gaussian process in time), or oracle",
    )
    fit.add_argument(
        "--kernel",
        default="auto",
        choices=["auto", "rbf", "matern52", "polynomial", "features"],
        help="GP kernel of the correction (default: auto, chosen by cross-validation among RBF lengthscales and a "
        "feature kernel with automatic relevance, as fit_correction does)",
    )
    fit.add_argument(
        "--lengthscale",
        default="cv",
        help="the kernel lengthscale: cv (default: chosen by how well the corrected model predicts held-out "
        "experiments), ml (marginal likelihood), or a number (fixed)",
    )
    fit.add_argument(
        "--refine",
        action="store_true",
        help="refine the correction through the ODE (fit_trajectories: single shooting) after the fit",
    )
    fit.add_argument("--outputscale", type=float, help="fix the kernel output scale (default: learned)")
    fit.add_argument("--noise-variance", type=float, help="fix the samples' noise variance (default: learned)")
    fit.add_argument("--degree", type=int, default=2, help="polynomial order or feature degree (default: 2)")
    fit.add_argument("--out", default="model.pt", help="output model file, .pt (default: %(default)s)")
    fit.add_argument("--quiet", action="store_true", help="no progress bar")
    fit.set_defaults(func=_fit)

    des = sub.add_parser(
        "design",
        help="choose the initial conditions that teach the most about the correction",
        description="Experimental design (paper section 4): pick BUDGET of the candidate initial conditions whose "
        "proxy trajectories (the known model's) maximise the information gain about F under the given "
        "GP prior; writes the picks in order with their marginal gains (nats, real-Gaussian "
        "convention: half the paper's complex-convention numbers).",
    )
    des.add_argument(
        "--candidates",
        required=True,
        help="candidate initial conditions, one per row (N, d): CSV/TXT (optional header row), .npy, "
        "or .npz (array 'candidates' or a single array)",
    )
    des.add_argument(
        "--system",
        required=True,
        help="built-in system name (paper_linear, paper_gravity) or 'module:function' / 'path/to/file.py:function' "
        "returning a torchmisspec.MisspecifiedSystem (its code is run)",
    )
    des.add_argument(
        "--times",
        required=True,
        help="observation times: 'start:stop:count' (equally spaced, e.g. 0:6:11) or a comma list",
    )
    des.add_argument("--budget", type=int, required=True, help="number of experiments K to choose")
    des.add_argument(
        "--kernel",
        default="rbf",
        choices=["rbf", "matern52", "polynomial"],
        help="GP kernel of the correction (default: rbf)",
    )
    des.add_argument("--lengthscale", type=float, default=1.0, help="kernel lengthscale l (default: 1.0)")
    des.add_argument("--outputscale", type=float, default=4e-5, help="kernel output scale (default: 4e-5)")
    des.add_argument(
        "--noise-variance",
        type=float,
        default=1e-4,
        help="variance of the noise on the correction samples (default: 1e-4)",
    )
    des.add_argument("--degree", type=int, default=2, help="polynomial order or feature degree (default: 2)")
    des.add_argument(
        "--method",
        default="lazy",
        choices=["lazy", "plain", "naive", "agnostic", "random", "greedy"],
        help="lazy greedy (default), plain greedy ('greedy' is its old name), naive greedy (reference), agnostic "
        "(ignores the known model), or random",
    )
    des.add_argument(
        "--criterion",
        default="information",
        choices=["information", "domain"],
        help="information about F (the paper's, default) or domain: the variance of F over the system's domain D",
    )
    des.add_argument(
        "--data",
        help="experiments already run (a table or .npz as for 'fit'): the design is conditioned on their samples "
        "and, by default, follows the corrected model's trajectories",
    )
    des.add_argument(
        "--derivative", default="auto", help="with --data: how dy/dt is estimated from the states (default: auto)"
    )
    des.add_argument(
        "--learn-hyperparameters",
        action="store_true",
        help="with --data: learn the kernel hyperparameters from the data by marginal likelihood instead of using "
        "--lengthscale/--outputscale/--noise-variance",
    )
    des.add_argument(
        "--proxy",
        choices=["known", "corrected"],
        help="trajectories the samples are predicted along: G alone or G + the GP's mean (default: corrected with "
        "--data, known without)",
    )
    des.add_argument("--partition", help="optional file with one integer region label per candidate")
    des.add_argument(
        "--capacities",
        help="most picks per region: 'label=count,...' or 'count,count,...' (indexed by label); needs --partition",
    )
    des.add_argument("--seed", type=int, default=0, help="seed of the random design (default: 0)")
    des.add_argument("--out", default="design.csv", help="output file, .csv or .json (default: %(default)s)")
    des.add_argument("--quiet", action="store_true", help="no progress bar")
    des.set_defaults(func=_design)
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
