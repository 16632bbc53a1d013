"""``torchmisspec design``: the next experiments, from a model, from data, or from a prior the user states."""

from __future__ import annotations

import argparse
import json

from .._errors import InputError
from ._common import (
    add_data_options,
    add_system_option,
    check_names,
    check_output,
    input_columns,
    known_state_names,
    load_model,
    read_controls,
    read_observations,
    read_states,
    seed,
    write_csv,
    written,
)
from ._tables import parse_times, read_table

__all__ = ["add_design"]

PRIOR = ("lengthscale", "outputscale", "noise_variance")


def _gp(args: argparse.Namespace, system, observed=None):
    """The design's GP: ``--model``, or fitted on ``--data``, or the prior the user gave; never a hidden one."""
    from ..gp import CorrectionGP

    given = {name: getattr(args, name) for name in PRIOR if getattr(args, name) is not None}
    if args.model is not None and (given or args.data is not None):
        raise InputError(
            "--model: expected the model alone (it holds its data and hyperparameters), got --data or a prior too; "
            "drop them"
        )
    if args.model is not None:
        return load_model(args.model, system), "the model " + args.model
    if given and len(given) != len(PRIOR):
        missing = ", ".join("--" + n.replace("_", "-") for n in PRIOR if n not in given)
        raise InputError(
            f"the prior: expected --lengthscale, --outputscale and --noise-variance together; missing {missing}"
        )
    if args.data is not None:
        observed = read_observations(args, system) if observed is None else observed
        if given:  # the user's prior, conditioned on the data
            from ..learning.samples.observations import correction_samples

            samples = correction_samples(observed, system, derivative=args.derivative)
            return CorrectionGP(kernel=args.kernel, **given).condition(samples), f"the given prior and {args.data}"
        from ..learning import Pipeline, Samples

        gp = Pipeline(samples=Samples(derivative=args.derivative)).fit(observed, system, progress=not args.quiet)
        return gp, f"a model fitted on {args.data}"
    if given:
        return CorrectionGP(kernel=args.kernel, **given), "the given prior"
    raise InputError(
        "design: no model to design with. Pass --model model.pt (written by 'fit'), --data observed.csv (a model is "
        "fitted with the defaults), or a prior before any data: --lengthscale, --outputscale and --noise-variance "
        "(the size of F in the units of dy/dt, squared, and the noise on its samples)"
    )


def _capacities(args: argparse.Namespace, n: int):
    import torch

    if args.partition is None:
        if args.capacities is not None:
            raise InputError("--capacities: expected --partition with it (a region label per candidate), got none")
        return None, None
    labels = torch.as_tensor(read_table(args.partition, "partition")[0]).reshape(-1)
    if labels.is_floating_point() and not bool((labels == labels.round()).all()):
        raise InputError(f"--partition: expected integer region labels, got fractional values in {args.partition}")
    if args.capacities is None:
        raise InputError("--capacities: expected the most picks per region with --partition, got none")
    try:
        if "=" in args.capacities:
            pairs = [(int(k), int(v)) for k, v in (kv.split("=") for kv in args.capacities.split(","))]
        else:
            pairs = list(enumerate(int(v) for v in args.capacities.split(",")))
    except ValueError as exc:
        raise InputError(
            f"--capacities: expected 'label=count,...' or 'count,count,...', got {args.capacities!r}"
        ) from exc
    labels_given = [k for k, _ in pairs]
    twice = next((k for k in labels_given if labels_given.count(k) > 1), None)
    if twice is not None:
        raise InputError(f"--capacities: expected each region label once, got {twice} twice in {args.capacities!r}")
    caps = dict(pairs) if "=" in args.capacities else [v for _, v in pairs]
    return labels.long(), caps


def _design(args: argparse.Namespace) -> int:
    import torch

    from ..systems import load_system

    out = check_output(args.out, (".csv", ".json"))
    system = load_system(args.system)
    input_columns(args, system)  # checked before the work (read with --controls)
    times = _times_and_checked_options(args, system)
    early = _gp(args, system) if args.model is not None else None  # a model file is checked before the candidates
    observed = read_observations(args, system) if args.data is not None and early is None else None  # read first
    known = known_state_names(system, None if early is None else early[0])
    if observed is not None and tuple(observed.state_names) != tuple(f"y{j}" for j in range(system.state_dim)):
        known = list(observed.state_names)  # the data's names: the candidates are read by them
    candidates, names, labels = read_states(args.candidates, "--candidates", args, system, known)
    partition, capacities = _capacities(args, candidates.shape[0])  # (region labels, most picks per region)
    controls = None
    if args.controls is not None:
        if labels is None:
            raise InputError(
                f"--candidates: expected an --experiment-column ({args.experiment_column!r}) labelling each candidate, "
                "so that its profile in --controls can be found"
            )
        controls = read_controls(args.controls, args, system, labels)
    gp, source = early or _gp(args, system, observed)  # a fit on --data comes last: after every cheap check
    names = check_names(gp, names, system, "--candidates")
    if system.parameters is not None and getattr(gp, "parameters_", None) is not None:
        system = system.at(gp.parameters_.mean)  # G's uncertain parameters at their posterior mean for the proxies
    if args.criterion != "information" and args.method not in ("lazy", "plain", "naive"):
        raise InputError(
            f"--criterion {args.criterion}: expected a greedy --method (lazy, plain or naive), got {args.method}"
        )
    from ..design import Partition

    partition = None if partition is None else Partition(partition, capacities)
    common = dict(system=system, times=times, gp=gp, progress=not args.quiet, partition=partition)
    plan = _plan(args, candidates, controls, common, torch.Generator().manual_seed(args.seed))
    when = None if args.samples_per_experiment is None else _measurement_times(args, plan, controls, common)
    units = "mean variance of F over D removed" if args.criterion == "domain" else "nats (real-Gaussian convention)"
    conditioned = plan.diagnostics.get("conditioned", 0)
    if out.suffix == ".json":
        _write_json(out, args, plan, dict(system=system.name, model=source, units=units, times=when), names, labels)
    else:
        label = [] if labels is None else [args.experiment_column]  # the candidates' own labels, when they have them
        rows = [
            [i, c, *([] if labels is None else [labels[c]]), g, *p, *([] if when is None else [_times(when[i])])]
            for i, (c, g, p) in enumerate(
                zip(plan.indices.tolist(), plan.gains.tolist(), plan.points.tolist(), strict=True)
            )
        ]
        extra = [] if when is None else ["measure_at"]
        write_csv(out, ["order", "index", *label, "gain", *names, *extra], rows)
    print(
        f"{plan.method} design of {len(plan)} experiments from {candidates.shape[0]} candidates on {system.name} "
        f"with {source}"
        + (f" (conditioned on {conditioned} samples)" if conditioned else "")
        + f": criterion {args.criterion} {plan.information_gain:.4g} {units}; indices {plan.indices.tolist()}; "
        + ("" if when is None else f"{args.samples_per_experiment} of the {len(times)} times chosen in each; ")
        + f"written to {out}"
    )
    return 0


def _times_and_checked_options(args: argparse.Namespace, system):
    """``--times`` read, and the options that must go together checked before any work: input profiles for a system
    with inputs (and only then, designed by information), the samples per experiment within the times, a readout
    with data."""
    if system.num_controls and args.controls is None:
        raise InputError(
            f"--system: '{system.name}' has inputs u(t) {list(system.control_names)}; a candidate experiment is an "
            "initial state and an input profile: pass --controls profiles.csv (columns: the --experiment-column "
            "labelling the rows of --candidates, the time, the inputs)"
        )
    if args.controls is not None and not system.num_controls:
        raise InputError(
            f"--controls: expected none, system '{system.name}' has no inputs u(t), got {args.controls!r}; drop it"
        )
    if args.controls is not None and args.criterion != "information":
        raise InputError(
            f"--controls: expected --criterion information (input profiles are designed by it), got {args.criterion}"
        )
    times = parse_times(args.times)
    if args.samples_per_experiment is not None and not 1 <= args.samples_per_experiment <= len(times):
        raise InputError(
            f"--samples-per-experiment: expected 1 to {len(times)} (the number of --times), got "
            f"{args.samples_per_experiment}"
        )
    if args.readout and args.data is None:  # a readout names columns of --data: nothing would read it
        raise InputError(
            f"--readout: expected --data whose columns it names (the design reads no other table), got "
            f"--readout {args.readout[0]!r} without --data; drop it, or fit on --data"
        )
    return times


def _plan(args: argparse.Namespace, candidates, controls, common: dict, generator):
    """The design by ``--method``: random (drawn with ``generator``), agnostic, or a greedy one (the stochastic
    greedy's draws with ``generator``)."""
    from .. import design

    if args.method == "random":
        return design.random(candidates, args.budget, generator=generator, controls=controls, **common)
    if args.method == "agnostic":
        return design.agnostic(candidates, args.budget, controls=controls, **common)
    draws = {"engine": design.Engine(generator=generator)} if args.method == "stochastic" else {}
    return design.greedy(
        candidates,
        args.budget,
        method=args.method,
        **draws,
        criterion=args.criterion,
        proxy=design.Proxy(args.proxy),
        controls=controls,
        **common,
    )


def _measurement_times(args: argparse.Namespace, plan, controls, common: dict) -> list[list[float]]:
    """``--samples-per-experiment``: the times to measure in each chosen experiment
    (:func:`~torchmisspec.design.sampling_times`)."""
    from .. import design

    picked = design.sampling_times(
        plan.points,
        common["times"],
        args.samples_per_experiment,
        system=common["system"],
        gp=common["gp"],
        criterion=args.criterion,
        proxy=design.Proxy(args.proxy),
        progress=not args.quiet,
        controls=None if controls is None else controls[plan.indices.tolist()],
    )
    return [[float(x) for x in t.tolist()] for t in picked.times]


def _write_json(out, args: argparse.Namespace, plan, about: dict, names, labels) -> None:
    """The design as JSON: the picks, their gains and points, and ``about`` (the system's and the model's names, the
    gains' units, the measurement times)."""
    text = json.dumps(
        {
            "system": about["system"],
            "model": about["model"],
            "method": plan.method,
            "budget": args.budget,
            "indices": plan.indices.tolist(),
            "gains": plan.gains.tolist(),
            "information_gain": plan.information_gain,
            "points": [dict(zip(names, p, strict=True)) for p in plan.points.tolist()],
            "labels": None if labels is None else [labels[i] for i in plan.indices.tolist()],
            "criterion": args.criterion,
            "conditioned_on_samples": plan.diagnostics.get("conditioned", 0),
            "proxy": plan.diagnostics.get("proxy"),
            "units": about["units"],
            "times": about["times"],
        },
        indent=2,
    )
    with written(out) as tmp:
        tmp.write_text(text)


def _times(values: list[float]) -> str:
    """A cell of measurement times, space separated (the CSV's cells are comma separated)."""
    return " ".join(f"{v:.6g}" for v in values)


def add_design(sub) -> None:
    des = sub.add_parser(
        "design",
        help="choose the next experiments: the candidate initial conditions that teach the most about F",
        description="Experimental design (paper section 4): pick BUDGET of the candidate initial conditions whose "
        "predicted trajectories carry the most information about F, given what is known: a fitted model (--model), "
        "data (--data: a model is fitted with the defaults), or, before any data, a prior you state "
        "(--lengthscale, --outputscale, --noise-variance). Writes the picks in order with their marginal gains.",
    )
    des.add_argument(
        "--candidates",
        required=True,
        help="candidate initial conditions, one per row (N, d): CSV/TSV/TXT with a header of state names (read with "
        "--state-columns; an --experiment-column labels the rows) or without one, "
        ".npy, or .npz (array 'candidates' or a single array)",
    )
    add_system_option(des)
    des.add_argument(
        "--times",
        required=True,
        help="observation times: 'start:stop:count' (equally spaced, e.g. 0:6:11) or a comma list",
    )
    des.add_argument("--budget", type=int, required=True, help="number of experiments K to choose")
    des.add_argument(
        "--samples-per-experiment",
        type=int,
        help="measure only this many of --times in each chosen experiment, chosen by the same criterion "
        "(design.sampling_times; written as a column measure_at of space separated times)",
    )
    des.add_argument(
        "--controls",
        help="for a system with inputs u(t): each candidate's input profile, a CSV/TSV/TXT with the "
        "--experiment-column (the labels of --candidates' rows; a state may be listed with several profiles), the "
        "--time-column and one column per input (--input-columns), each profile's rows its samples (--input-kind)",
    )
    des.add_argument("--model", help="a model file written by 'fit' (its data condition the design)")
    add_data_options(des, required=False, help="experiments already run, as for 'fit': a model is fitted on them")
    des.add_argument("--derivative", default="auto", help="with --data: how dy/dt is estimated (default: auto)")
    des.add_argument("--kernel", default="rbf", choices=["rbf", "matern52", "polynomial"], help="the prior's kernel")
    des.add_argument("--lengthscale", type=float, help="the prior's lengthscale (with --outputscale, --noise-variance)")
    des.add_argument("--outputscale", type=float, help="the prior's output scale: the variance of F")
    des.add_argument("--noise-variance", type=float, help="the variance of the noise on the samples of F")
    des.add_argument(
        "--method",
        default="lazy",
        choices=["lazy", "plain", "naive", "stochastic", "agnostic", "random"],
        help="lazy greedy (default), plain greedy, naive greedy (reference), stochastic greedy (the best of a random "
        "draw per pick, for 10^5 candidates and more; seeded by --seed), agnostic (ignores the known model), random",
    )
    des.add_argument(
        "--criterion",
        default="information",
        choices=["information", "domain"],
        help="information about F (the paper's, default) or domain: the variance of F over the system's domain D",
    )
    des.add_argument(
        "--proxy",
        choices=["known", "corrected"],
        help="trajectories the samples are predicted along: G alone or G + the GP's mean (default: corrected with a "
        "fitted model, known without)",
    )
    des.add_argument("--partition", help="optional file with one integer region label per candidate")
    des.add_argument(
        "--capacities",
        help="most picks per region: 'label=count,...' or 'count,count,...' (indexed by label); needs --partition",
    )
    des.add_argument("--seed", type=seed, default=0, help="seed of the random design (default: 0)")
    des.add_argument("--out", default="design.csv", help="output file, .csv or .json (default: %(default)s)")
    des.add_argument("--quiet", action="store_true", help="no progress bars")
    des.set_defaults(func=_design)
