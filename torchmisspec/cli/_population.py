"""``torchmisspec population``: experiments that differ in some of G's parameters (subjects, trees, batches).

Reads the lab's table as ``fit`` does (one experiment per subject: ``--experiment-column``), fits the population
(:func:`~torchmisspec.population.fit.fit_population`: the parameters named by ``--vary`` differ between subjects,
log-normal by default, shifted by the covariates of ``--covariate``), prints the population's values beside the
classical answer's and writes every subject's parameters to a CSV. With ``--next-times`` and ``--budget``, it also
designs the next subject's sampling times (and, with several ``--next-initial``, its starting state: a dose).
"""

from __future__ import annotations

import argparse

from .._errors import InputError
from ._common import add_data_options, add_system_option, check_output, read_observations, write_csv


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
    from ..data import experiment_labels, read_covariates
    from ..population import Population
    from ..population.distributions import DISTRIBUTIONS
    from ..population.fit import fit_population
    from ..systems import load_system

    out = check_output(args.out, (".csv",))
    varying = _names(args.vary, "--vary")
    covariates = _covariates(args.covariate)
    population = Population(varying, distribution=DISTRIBUTIONS[args.distribution](), covariates=covariates)
    system = load_system(args.system)
    population.indices(system)  # the names checked before the work
    request = _design_request(args, system, population)
    observed = read_observations(args, system)
    columns = list(population.covariate_names)
    values = read_covariates(args.data, columns, experiment_column=args.experiment_column or None) if columns else None
    fit = fit_population(observed, system, population, covariates=values, noise=args.noise, progress=not args.quiet)
    print(
        f"fitted a population of {observed.num_experiments} experiments of '{system.name}', {', '.join(varying)} "
        f"varying ({args.distribution}), noise {fit.noise.name!r}:"
    )
    print(fit.summary())
    labels = experiment_labels(args.data, args.experiment_column or None) if not args.data.endswith(".npz") else None
    labels = labels or [str(k + 1) for k in range(observed.num_experiments)]
    names = list(system.parameters.names)
    rows = [[label, *(f"{float(v):.6g}" for v in theta)] for label, theta in zip(labels, fit.thetas, strict=True)]
    write_csv(out, [args.experiment_column or "experiment", *names], rows)
    print(f"every experiment's parameters written to {out}")
    if request is not None:
        _design(args, fit, request)
    return 0


def _design_request(args: argparse.Namespace, system, population):
    """``(times, initial states, covariates)`` of the next subject's design, checked before the work (``None``
    without ``--next-times``)."""
    import torch

    if not args.next_times:
        return None
    if args.budget is None:
        raise InputError("--budget: expected the number of samples of the next subject with --next-times, got none")
    given = dict(_pair(item) for item in args.next_covariate or [])
    wanted = list(population.covariate_names)
    if sorted(given) != sorted(wanted):
        raise InputError(
            f"--next-covariate: expected the next subject's {wanted} as NAME=VALUE (one each), got {sorted(given)}"
        )
    d = system.state_dim
    starts = [_numbers(s, "--next-initial") for s in (args.next_initial or [])]
    if not starts or any(len(s) != d for s in starts):
        raise InputError(
            f"--next-initial: expected the next subject's initial state, {d} comma separated numbers in the system's "
            f"state order {list(system.state_names or [])} (repeat it for several candidates), got {starts or None}"
        )
    times = torch.tensor(_numbers(args.next_times, "--next-times"), dtype=torch.float64)
    return times, torch.tensor(starts, dtype=torch.float64), given or None


def _design(args: argparse.Namespace, fit, request) -> None:
    from ..population.design import design_subject

    times, starts, covariates = request
    design = design_subject(fit, times, args.budget, initial_states=starts, covariates=covariates)
    state = ", ".join(f"{v:g}" for v in design.initial_state.tolist())
    print(
        f"next subject: sample at {', '.join(f'{t:g}' for t in design.times.tolist())} from the initial state "
        f"({state}); {design.description}"
    )


def add_population(sub) -> None:
    from ..noise import NOISE_MODELS
    from ..population.distributions import DISTRIBUTIONS

    pop = sub.add_parser(
        "population",
        help="fit experiments that differ in some of G's parameters (subjects, trees, batches), F shared",
        description=__doc__.split("\n\n")[1],
    )
    add_data_options(pop, required=True, help="observed trajectories, one experiment per subject (as for 'fit')")
    add_system_option(pop)
    pop.add_argument("--vary", required=True, help="comma separated names of G's parameters that differ between "
                     "experiments, e.g. ka,ke,V")  # fmt: skip
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
    pop.add_argument("--next-times", help="comma separated candidate sampling times of the next subject")
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
    pop.add_argument("--quiet", action="store_true", help="no progress bars")
    pop.set_defaults(func=_population)
