"""``torchmisspec population``: experiments that differ in some of G's parameters (subjects, trees, batches).

Reads the lab's table as ``fit`` does (one experiment per subject: ``--experiment-column``), fits the population
(:func:`~torchmisspec.population.fit.fit_population`: the parameters named by ``--vary`` differ between subjects,
log-normal by default, shifted by the covariates of ``--covariate``), prints the population's values beside the
classical answer's and writes every subject's parameters to a CSV. With ``--next-times`` and ``--budget``, it also
designs the next subject's sampling times (and, with several ``--next-initial``, its starting state: a dose). With
``--predict-times``, it predicts the next subject's path with its band: from its first measurements (``--first``, a
table of that subject's rows), or from the population alone (its ``--next-initial``). ``--save`` writes the fitted
population to a file, and ``--fit`` reads it back instead of fitting ``--data``: a lab fits once, and designs and
predicts each next subject later.
"""

from __future__ import annotations

import argparse

from .._errors import InputError
from ._common import add_data_options, add_system_option, check_output, read_controls, read_observations, write_csv
from ._predict import _table
from ._tables import parse_times


def _names(text: str, option: str) -> list[str]:
    names = [n.strip() for n in text.split(",")]
    if not all(names) or len(set(names)) != len(names):
        raise InputError(f"{option}: expected distinct comma separated names, got {text!r}")
    return names


def _numbers(text: str, option: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"{option}: expected comma separated numbers, got {text!r}") from None


def _pair(item: str) -> tuple[str, float]:
    name, _, value = item.partition("=")
    number = _numbers(value, "--next-covariate") if value.strip() else []
    if not name.strip() or len(number) != 1:
        raise InputError(f"--next-covariate: expected NAME=VALUE (e.g. weight=70), got {item!r}")
    return name.strip(), number[0]


def _covariates(items: list[str] | None) -> dict[str, list[str]]:
    """``--covariate PARAMETER=COLUMN`` (repeated) as ``{parameter: [columns]}``."""
    out: dict[str, list[str]] = {}
    for item in items or []:
        name, _, column = item.partition("=")
        if not name.strip() or not column.strip():
            raise InputError(f"--covariate: expected PARAMETER=COLUMN (e.g. V=weight), got {item!r}")
        out.setdefault(name.strip(), []).append(column.strip())
    return out


def _population(args: argparse.Namespace) -> int:
    from ..population.fit import PopulationFit
    from ..systems import load_system

    if (args.data is None) == (args.fit is None):
        got = "both" if args.data else "neither"
        raise InputError(f"--data / --fit: expected a table to fit (--data) or a population saved with --save (--fit), "
                         f"got {got}")  # fmt: skip
    save = None if args.save is None else check_output(args.save, (".pt",), "--save")
    system = load_system(args.system)
    if args.fit is not None:
        fit = PopulationFit.load(args.fit, system)
        population, observed = fit.population, fit.data
    else:
        out = check_output(args.out, (".csv",))
        population = _declared(args, system)
    request = _design_request(args, system, population)
    prediction = _prediction_request(args, system, population)
    if args.fit is None:
        fit, observed = _fit(args, system, population, out)
    else:
        print(f"loaded a population of {observed.num_experiments} experiments of '{system.name}' from {args.fit}:")
        print(fit.summary())
    if save is not None:
        fit.save(save)
        print(f"the fitted population saved to {save} (design or predict the next subject from it with --fit {save})")
    if request is not None:
        _design(args, fit, request)
    if prediction is not None:
        _predict_next(args, fit, prediction, observed)
    return 0


def _declared(args: argparse.Namespace, system):
    """The population ``--vary``, ``--distribution`` and ``--covariate`` declare, checked against ``system``."""
    from ..population import Population
    from ..population.distributions import DISTRIBUTIONS

    if not args.vary:
        raise InputError("--vary: expected the comma separated names of G's parameters that differ between "
                         "experiments with --data, e.g. ka,ke,V, got none")  # fmt: skip
    varying = _names(args.vary, "--vary")
    population = Population(
        varying, distribution=DISTRIBUTIONS[args.distribution](), covariates=_covariates(args.covariate)
    )
    try:  # the names checked before the work, in the command line's words
        population.indices(system)
    except InputError as exc:
        message = str(exc).replace("varying: ", "--vary: ", 1)
        raise InputError(
            message.replace(
                "declare them in MisspecifiedSystem(", "declare them in the model file's MisspecifiedSystem("
            )
        ) from None
    return population


def _fit(args: argparse.Namespace, system, population, out):
    """The population fitted to ``--data``, its summary printed and every experiment's parameters written to
    ``out``: ``(fit, observed)``."""
    from ..data import experiment_labels, read_covariates
    from ..population.fit import fit_population

    observed = read_observations(args, system)
    columns = list(population.covariate_names)
    values = read_covariates(args.data, columns, experiment_column=args.experiment_column or None) if columns else None
    fit = fit_population(observed, system, population, covariates=values, noise=args.noise, progress=not args.quiet)
    print(
        f"fitted a population of {observed.num_experiments} experiments of '{system.name}', "
        f"{', '.join(population.varying)} varying ({args.distribution}), noise {fit.noise.name!r}:"
    )
    print(fit.summary())
    labels = experiment_labels(args.data, args.experiment_column or None) if not args.data.endswith(".npz") else None
    labels = labels or [str(k + 1) for k in range(observed.num_experiments)]
    names = list(system.parameters.names)
    rows = [[label, *(f"{float(v):.6g}" for v in theta)] for label, theta in zip(labels, fit.thetas, strict=True)]
    write_csv(out, [args.experiment_column or "experiment", *names], rows)
    print(f"every experiment's parameters written to {out}")
    return fit, observed


def _design_request(args: argparse.Namespace, system, population):
    """``(times, initial states, covariates, controls)`` of the next subject's design, checked before the work
    (``None`` without ``--next-times``)."""
    import torch

    if not args.next_times:
        return None
    if args.budget is None:
        raise InputError("--budget: expected the number of samples of the next subject with --next-times, got none")
    controls = _next_controls(args, system, "--next-times")
    given = _next_covariates(args, population)
    starts = _next_initial(args, system)
    if not starts:
        raise InputError(_initial_message(system, "(repeat it for several candidates)", starts))
    times = parse_times(args.next_times, "--next-times")  # the forms --predict-times takes
    return times, torch.tensor(starts, dtype=torch.float64), given, controls


def _next_covariates(args: argparse.Namespace, population) -> dict | None:
    """The next subject's covariates of ``--next-covariate``, one for each the population names."""
    given = dict(_pair(item) for item in args.next_covariate or [])
    wanted = list(population.covariate_names)
    if sorted(given) != sorted(wanted):
        raise InputError(
            f"--next-covariate: expected the next subject's {wanted} as NAME=VALUE (one each), got {sorted(given)}"
        )
    return given or None


def _next_initial(args: argparse.Namespace, system) -> list[list[float]]:
    """The candidate initial states of ``--next-initial``, each of the system's size."""
    starts = [_numbers(s, "--next-initial") for s in (args.next_initial or [])]
    if any(len(s) != system.state_dim for s in starts):
        raise InputError(_initial_message(system, "(repeat it for several candidates)", starts))
    return starts


def _initial_message(system, repeat: str, starts) -> str:
    return (
        f"--next-initial: expected the next subject's initial state, {system.state_dim} comma separated numbers in "
        f"the system's state order {list(system.state_names or [])} {repeat}, got {starts or None}"
    )


def _prediction_request(args: argparse.Namespace, system, population):
    """``(times, first, y0, covariates)`` of the next subject's prediction, checked before the work (``None``
    without ``--predict-times``): ``first`` its measurements (``--first``) or ``y0`` its initial state."""
    import torch

    if not args.predict_times:
        if args.first:
            raise InputError(
                "--first: expected --predict-times with it (the times to predict the subject at), got none"
            )
        if args.controls and not args.next_times:
            raise InputError("--controls: expected --predict-times or --next-times with it (the next subject's "
                             "prediction or design it is the input profile of), got neither")  # fmt: skip
        return None
    if not 0 < args.level < 1:
        raise InputError(f"--level: expected a band's coverage in (0, 1), got {args.level}")
    controls = _next_controls(args, system, "--predict-times")
    times = parse_times(args.predict_times, "--predict-times")
    if not bool(torch.isfinite(times).all()) or bool((times.diff() <= 0).any()):
        raise InputError(f"--predict-times: expected finite, strictly increasing times, got {args.predict_times!r}")
    check_output(args.predict_out, (".csv",), "--predict-out")
    covariates = _next_covariates(args, population)
    if args.first:  # its subject column read where it has one (two subjects' rows are then refused by name)
        from ..data._tables import header

        column = args.experiment_column if args.experiment_column in (header(args.first) or []) else ""
        first = read_observations(
            argparse.Namespace(**{**vars(args), "data": args.first, "experiment_column": column}), system
        )
        if first.num_experiments != 1:  # a subject column there labels them: one subject's rows are wanted
            raise InputError(
                f"--first: expected the next subject's first measurements (one subject's rows), got "
                f"{first.num_experiments} subjects in {args.first} (its column {args.experiment_column!r}); keep the "
                "next subject's rows only"
            )
        from ..population.predict import times_from

        times_from(times, first, "--predict-times")  # refused before the fit
        return times, first, None, covariates, controls
    starts = _next_initial(args, system)
    if len(starts) != 1:
        raise InputError(_initial_message(system, "(one, or its first measurements with --first)", starts))
    return times, None, torch.tensor(starts[0], dtype=torch.float64), covariates, controls


def _next_controls(args: argparse.Namespace, system, wanted_by: str):
    """The next subject's input profile of ``--controls`` (one profile; its experiment column, if any, not read),
    required for a system with inputs and refused for one without."""
    if not system.num_controls:
        if args.controls:
            raise InputError(f"--controls: expected none for system '{system.name}' (it takes no inputs u(t)), got "
                             f"{args.controls!r}")  # fmt: skip
        return None
    if not args.controls:
        raise InputError(
            f"--controls: expected the next subject's input profile for {wanted_by} (system '{system.name}' takes "
            f"{list(system.control_names)}), got none; give a table with the --time-column and one column per input, "
            f"its rows the profile's samples over the next subject's times"
        )
    return read_controls(args.controls, argparse.Namespace(**{**vars(args), "experiment_column": ""}), system, [""])


def _predict_next(args: argparse.Namespace, fit, request, observed) -> None:
    """The next subject's path and band at ``--predict-times``, written to ``--predict-out``."""
    import torch

    from ..population.predict import predict_subject

    times, first, y0, covariates, controls = request
    cal = fit.calibration
    if first is not None and cal is not None and first.num_times != cal.first:  # calibrated for its count, if it can be
        again = fit.recalibrated(first.num_times, progress=not args.quiet)
        fit = again if again.calibration is not None else fit
    generator = torch.Generator().manual_seed(0)
    pred = predict_subject(fit, y0, times, covariates=covariates, first=first, controls=controls, generator=generator)
    post = pred.posterior
    if args.measurements:  # the band its new measurements fall in: the population's residual scale, its noise model
        post = post.measured(fit.noise, fit.nlme.modes.scale, generator=torch.Generator().manual_seed(1))
    lower, upper = post.interval(args.level)
    names = list(post.state_names or [f"y{i}" for i in range(post.samples.shape[-1])])
    header, rows = _table(post, lower, upper, times.tolist(), names, ["next"], None, args)  # as `predict` writes
    out = check_output(args.predict_out, (".csv",), "--predict-out")
    write_csv(out, header, rows)
    varying = fit.nlme.layout.vary
    values = ", ".join(f"{fit.system.parameters.names[i]} = {float(pred.theta[i]):.4g}" for i in varying)
    source = f"its first {first.num_times} measurements" if first is not None else "the population alone"
    print(
        f"next subject from {source}: {values}; its path at {times.numel()} times with the central "
        f"{args.level:.0%} band{' of new measurements' if args.measurements else ''} written to {out}"
        f"{_beyond(times, observed, fit)}{_calibrated(pred, fit, first)}"
    )


def _calibrated(pred, fit, first) -> str:
    """A note of how the band was calibrated on held-out subjects (from their first measurements, or from the
    population alone)."""
    cal = fit.calibration_for(first)
    if cal is None:
        return ""
    if first is not None and first.num_times != cal.first:
        return (
            f"; its band not calibrated: no held-out subject could be checked from its first {first.num_times} "
            f"measurements (more measured after them, F's samples recorded), the fit's calibration is for {cal.first}"
        )
    how = "widened" if pred.band_scale >= 1 else "narrowed"
    source = "from the population alone" if first is None else f"from their first {cal.first}"
    note = f"; its band {how} to {pred.band_scale:.3g} times its spread, as held-out subjects needed {source}"
    return note + ("" if cal.f_draws or cal.other is None else ", the paths under F's mean (its draws scored worse)")


def _beyond(times, observed, fit) -> str:
    """A note where the prediction runs past the population's last measurement (none without the data)."""
    if observed is None:
        return ""
    last = float(observed.padded()[0].max())
    if float(times.max()) <= last:
        return ""
    kind = "F = 0 kept: G alone there" if fit.known_model else "F there is extrapolated, its band wider"
    return f" (past the data's last time {last:g}: {kind})"


def _design(args: argparse.Namespace, fit, request) -> None:
    import torch

    from ..population.design import design_subject

    times, starts, covariates, controls = request
    # the design's drawn subjects seeded: the same command gives the same design
    g = torch.Generator().manual_seed(0)
    design = design_subject(
        fit, times, args.budget, initial_states=starts, covariates=covariates, controls=controls, generator=g
    )
    state = ", ".join(f"{v:g}" for v in design.initial_state.tolist())
    print(
        f"next subject: sample at {', '.join(f'{t:g}' for t in design.times.tolist())} from the initial state "
        f"({state}) at {float(times[0]):g}; {design.description}"
    )


def add_population(sub) -> None:
    from ..noise import NOISE_MODELS
    from ..population.distributions import DISTRIBUTIONS

    pop = sub.add_parser(
        "population",
        help="fit experiments that differ in some of G's parameters (subjects, trees, batches), F shared",
        description=__doc__.split("\n\n")[1],
    )
    add_data_options(pop, required=False, help="observed trajectories, one experiment per subject (as for 'fit'); "
                     "or --fit")  # fmt: skip
    pop.add_argument("--fit", help="a population saved with --save (.pt), instead of fitting --data: design or "
                     "predict the next subject from it (--system the one it was fitted with)")  # fmt: skip
    pop.add_argument("--save", help="write the fitted population to this .pt file (tensors and plain values only)")
    add_system_option(pop)
    pop.add_argument("--vary", help="comma separated names of G's parameters that differ between experiments, e.g. "
                     "ka,ke,V (with --data)")  # fmt: skip
    pop.add_argument(
        "--distribution",
        default="lognormal",
        choices=list(DISTRIBUTIONS),
        help="their population distribution (default: %(default)s)",
    )
    pop.add_argument(
        "--covariate",
        action="append",
        metavar="PARAMETER=COLUMN",
        help="a column holding one value per experiment that shifts a varying parameter's typical value, e.g. "
        "V=weight (repeat for several)",
    )
    pop.add_argument("--noise", default="auto", choices=["auto", *NOISE_MODELS], help="as for 'fit'")
    pop.add_argument("--out", default="subjects.csv", help="every experiment's parameters, .csv (default: %(default)s)")
    pop.add_argument(
        "--next-times",
        help="times of the next subject, as --predict-times takes them (start:stop:count, a comma list or a file "
        "of times): the first is that of its initial state (--next-initial, never sampled), the others the "
        "candidate sampling times",
    )
    pop.add_argument("--budget", type=int, help="how many of them to sample")
    pop.add_argument(
        "--next-initial",
        action="append",
        help="a candidate initial state of the next subject, comma separated in the system's state order (repeat "
        "for several, e.g. dose levels)",
    )
    pop.add_argument(
        "--next-covariate",
        action="append",
        metavar="NAME=VALUE",
        help="the next subject's covariate (repeat for each one --covariate names)",
    )
    pop.add_argument("--predict-times", help="times to predict the next subject's path at, comma separated or "
                     "start:stop:count; with --first, from its first measurement's time on")  # fmt: skip
    pop.add_argument("--first", help="the next subject's first measurements, a table laid out as --data (its rows "
                     "only); without it the prediction is from the population alone, from --next-initial")  # fmt: skip
    pop.add_argument(
        "--controls",
        help="for a system with inputs u(t): the next subject's input profile for --predict-times and --next-times, "
        "a table with the --time-column and one column per input (named as the system's controls, or "
        "--input-columns), its rows the profile's samples (--input-kind)",
    )
    pop.add_argument("--predict-out", default="next_subject.csv", help="the next subject's path and band, .csv "
                     "(default: %(default)s)")  # fmt: skip
    pop.add_argument("--level", type=float, default=0.9, help="the band's coverage (default: %(default)s)")
    pop.add_argument("--measurements", action="store_true", help="the band of the next subject's new measurements "
                     "(its states' band widened by the population's residual scale), not of its states")  # fmt: skip
    pop.add_argument("--quiet", action="store_true", help="no progress bars")
    pop.set_defaults(func=_population)
