"""``torchmisspec fit`` and ``torchmisspec calibrate``: learn the correction from a lab's table, calibrate its bands."""

from __future__ import annotations

import argparse
import math

from .._errors import InputError
from ..learning.choice._time_pieces import MIN_PIECE
from ..noise import NOISE_MODELS
from ._common import (
    add_data_options,
    add_system_option,
    check_names,
    check_output,
    describe_system,
    load_model,
    read_observations,
    written,
)

__all__ = ["POSSIBLE_TERM", "add_calibrate", "add_fit"]

#: ``fit`` names the removed terms of a feature kernel whose chance of being present is at least this.
POSSIBLE_TERM = 0.05


def _state_noise(text: str, system=None):
    """``--state-noise``: auto, a percentage, a number, or one number per state (of ``system``, when given)."""
    text = text.strip()
    if text == "auto":
        return text
    if text.endswith("%"):
        try:
            value = float(text[:-1])
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value >= 0):
            raise InputError(f"--state-noise: expected a percentage >= 0 (finite), such as 2%, got {text!r}")
        return text
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(
            f"--state-noise: expected auto, a percentage such as 2%, a standard deviation or one per state "
            f"(comma separated), got {text!r}"
        ) from None
    bad = [v for v in values if not (math.isfinite(v) and v >= 0)]
    if bad:
        raise InputError(f"--state-noise: expected standard deviations >= 0 (finite), got {bad[0]}")
    if system is not None and len(values) not in (1, system.state_dim):
        raise InputError(
            f"--state-noise: expected one standard deviation or {system.state_dim} (one per state of system "
            f"'{system.name}'), got {len(values)}"
        )
    return values[0] if len(values) == 1 else values


def _check_level(level: float) -> None:
    if not 0 < level < 1:
        raise InputError(f"--level: expected a band's coverage in (0, 1), got {level}")


def _calibrate(model, observed, args: argparse.Namespace):
    return model.calibrate(
        observed, level=args.level, state_noise=_state_noise(args.state_noise), progress=not args.quiet
    )


def _fit(args: argparse.Namespace) -> int:
    from ..learning import Pipeline, Refinement, Samples
    from ..prediction.dynamics import CorrectedODE
    from ..systems import load_system

    out = check_output(args.out, (".pt",))
    _check_level(args.level)  # checked before the work
    _state_noise(args.state_noise)
    system = load_system(args.system)
    _state_noise(args.state_noise, system)
    observed = read_observations(args, system)
    refinement = Refinement(through_ode=True if args.refine else None)
    pipeline = Pipeline(samples=Samples(derivative=args.derivative), refinement=refinement, noise=args.noise)
    gp = pipeline.fit(observed, system, progress=not args.quiet)
    times = f"{min(observed.lengths)}-{max(observed.lengths)}" if observed.is_ragged else str(observed.num_times)
    print(
        f"fitted the correction of '{system.name}' on {len(gp.samples_)} samples ({observed.num_experiments} "
        f"experiment{'s' if observed.num_experiments != 1 else ''} x {times} times, derivative "
        f"{_derivative(args, gp)}, noise {gp.noise_.name!r}): {gp!r}"
    )
    _print_choice(gp, system)
    _print_learned(gp, observed)
    if gp.weights is not None:  # a feature kernel: its terms, in the data's names
        _print_terms(gp, system, observed)
    if not args.no_calibrate:
        if observed.num_experiments < 2:
            print(
                "bands not calibrated: with one experiment, 'torchmisspec calibrate' holds out pieces of its time "
                f"(every state measured, at least {2 * MIN_PIECE} times); each piece is forecast by a model fitted on "
                "the others, so the bands come out wider than the full fit's error"
            )
        else:
            print(f"calibrated bands: {_calibrate(CorrectedODE(system, gp), observed, args)}")
    gp.system_ = describe_system(system)  # later commands check they are given the same system
    with written(out) as tmp:
        gp.save(tmp)
    print(f"written to {out}")
    return 0


def _derivative(args, gp) -> str:
    """The estimator asked for, and what ``auto`` chose (with the edge samples it left out)."""
    used = getattr(gp, "derivative_", None)
    return f"{args.derivative!r}" if used is None or args.derivative != "auto" else f"'auto': {used}"


def _print_choice(gp, system) -> None:
    """What the fit chose and why: the known model kept alone, the cross-validation's choice against the known model,
    and with one trajectory the refined feature kernel against that choice."""
    cv = gp.cross_validation_
    if getattr(gp, "known_model_", False):
        fitted = ", its parameters fitted" if system.parameters is not None else ""
        print(
            f"kept the known model alone (F = 0{fitted}): the held-out data do not support a correction (the warning "
            "above says how they were tested)"
        )
    if cv is not None:
        # partly measured data: the held-out errors compare with the data completed by the first fitted model
        where = "" if getattr(gp, "identifiability_", None) is None else " (on the data completed through the ODE)"
        if getattr(gp, "known_model_", False):  # no candidate chosen: the best of them is not the model saved
            chose = f"best candidate {cv.best}, not kept"
        else:
            chose = f"chose {cv.best}"
        at = "" if cv.known_fitted is None else " at the parameters fitted with the correction"
        own = "" if cv.known_fitted is None else f"; {cv.known_fitted:.4g} with its own parameters fitted (F = 0)"
        print(
            f"cross-validation ({cv.folds} folds){where}: {chose}; held-out error {min(cv.scores):.4g}; the known "
            f"model alone: {cv.baseline:.4g}{at} (the gain over it {'' if cv.significant else 'NOT '}significant)"
            f"{own}"
        )
    if getattr(gp, "refinement_", None) is not None and getattr(gp, "identifiability_", None) is None:
        print(
            "then refined through the ODE: F fitted to the measured trajectories themselves, not to derivative "
            "estimates (where those are rough, as on sparse times, or for a chosen feature kernel; --refine always)"
        )
    rival = getattr(gp, "one_trajectory_rival_", None)
    if rival is not None:  # one trajectory: the refined feature kernel against that choice, on the last piece
        kept = rival["refined features"] < rival["chosen"]
        print(
            f"the feature kernel refined through the ODE, forecasting the last time piece: misfit "
            f"{rival['refined features']:.4g} against {rival['chosen']:.4g} for the cross-validation's choice and "
            f"{rival['known model']:.4g} for the known model alone: " + ("kept it" if kept else "kept the choice")
        )


def _print_learned(gp, observed) -> None:
    """What the fit learned besides F: the unmeasured states estimated through the ODE (and what the measurements
    see of them), and the posterior of G's uncertain parameters."""
    report = getattr(gp, "identifiability_", None)
    if report is not None:  # partly measured states: what the measurements see
        unmeasured = ", ".join(report.unmeasured)
        summary = report.summary().replace("\n", "\n  ")
        print(
            f"not measured (in some experiment): {unmeasured}; estimated through the ODE from the measured states"
            + (" and readings" if observed.readout is not None else "")
        )
        print(f"  {summary}")
    if getattr(gp, "parameters_", None) is not None:  # G's uncertain parameters, learned with F
        print("uncertain parameters of G, posterior mean +- sd:\n  " + gp.parameters_.summary().replace("\n", "\n  "))


def _print_terms(gp, system, observed) -> None:
    """A feature kernel's terms of each correction output, in the data's names (states, then the inputs'
    columns): those kept, and the removed ones whose chance of being present is at least :data:`POSSIBLE_TERM` (they
    widen the bands)."""
    names = list(observed.state_names)
    every = names + ([] if observed.controls is None else list(observed.controls.names))
    terms = list(gp.terms([every[i] for i in system.correction_inputs], all_terms=True))
    for o, j in enumerate(system.correction_outputs):
        kept = [str(t) for t in terms if t.output == o and t.weight > 0]
        line = f"correction of d{names[j]}/dt: " + (" ".join(kept) if kept else "0 (no term kept)")
        maybe = [t for t in terms if t.output == o and t.weight == 0 and t.inclusion >= POSSIBLE_TERM]
        if maybe:  # removed terms the data could not rule out (their chance widens the bands)
            maybe = sorted(maybe, key=lambda t: -t.inclusion)
            line += "; possibly also " + ", ".join(f"{t.name} (chance {t.inclusion:.2f})" for t in maybe)
        print(line)


def _recalibrate(args: argparse.Namespace) -> int:
    from ..learning.samples.observations import correction_samples
    from ..prediction.dynamics import CorrectedODE
    from ..systems import load_system

    out = check_output(args.out or args.model, (".pt",))
    _check_level(args.level)  # checked before the work
    _state_noise(args.state_noise)
    system = load_system(args.system)
    _state_noise(args.state_noise, system)
    gp = load_model(args.model, system)
    observed = read_observations(args, system)
    if tuple(observed.state_names) != tuple(f"y{j}" for j in range(observed.state_dim)):
        check_names(gp, list(observed.state_names), system, "--data")
    model = CorrectedODE(system, gp)
    # partly measured data: the samples of the data completed by the model (its paths where nothing was measured)
    samples = correction_samples(model.complete(observed), system, derivative=args.derivative)
    result = model.calibrate(
        observed, samples, level=args.level, state_noise=_state_noise(args.state_noise), progress=not args.quiet
    )
    with written(out) as tmp:
        gp.save(tmp)
    print(f"calibrated bands: {result}; written to {out}")
    return 0


def _calibration_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--level", type=float, default=0.9, help="the band to calibrate (default: %(default)s)")
    parser.add_argument(
        "--state-noise",
        default="auto",
        help="noise on the measured states: auto (default: estimated from the data), a percentage of the state "
        "(2%%), a standard deviation, or one per state (comma separated)",
    )


def add_fit(sub) -> None:
    fit = sub.add_parser(
        "fit",
        help="learn the correction F from a table of observed trajectories, calibrate its bands, save the model",
        description="Learn the missing term F of dy/dt = G(y) + F(y) from observed trajectories with the library's "
        "defaults (torchmisspec.fit_correction: dy/dt estimated from the states, the correction model chosen by "
        "cross-validation on held-out experiments), calibrate its uncertainty bands on held-out experiments "
        "(CorrectedODE.calibrate; a few seconds, --no-calibrate to skip), and save it with its calibration (read it "
        "back with torchmisspec.CorrectionGP.load, or pass it to 'predict', 'calibrate' and 'design').",
    )
    add_data_options(
        fit,
        required=True,
        help="observed trajectories: a .csv, .tsv or .txt table with a header row (one row per experiment and time, "
        "rows in any order) or an .npz written by Trajectories.save",
    )
    add_system_option(fit)
    fit.add_argument(
        "--derivative",
        default="auto",
        help="how dy/dt is estimated from the states: auto (default: the estimator whose self-check on the known "
        "model is best), central, smooth, gp (a Gaussian process in time)",
    )
    fit.add_argument(
        "--noise",
        default="auto",
        choices=["auto", *NOISE_MODELS],
        help="how the states' errors are alike, for the model choice, the parameters' fit and the bands: additive "
        "(one size), relative (log-normal, positive states), counts (log(1 + count): spread growing with the count), "
        "poisson (counts of independent events, their dispersion fitted); auto (default): relative when every "
        "measured state is positive and spans a factor of 5 or more, counts for whole numbers with zeros, additive "
        "otherwise",
    )
    fit.add_argument("--refine", action="store_true", help="always refine the correction through the ODE")
    fit.add_argument("--no-calibrate", action="store_true", help="save the model without calibrating its bands")
    _calibration_options(fit)
    fit.add_argument("--out", default="model.pt", help="output model file, .pt (default: %(default)s)")
    fit.add_argument("--quiet", action="store_true", help="no progress bars")
    fit.set_defaults(func=_fit)


def add_calibrate(sub) -> None:
    cal = sub.add_parser(
        "calibrate",
        help="calibrate a saved model's uncertainty bands on the experiments it was fitted on",
        description="Hold out folds of the experiments, refit, and scale the bands until they cover the held-out "
        "observations at the level (CorrectedODE.calibrate); the calibration is saved in the model file.",
    )
    cal.add_argument("--model", required=True, help="the model file written by 'fit'")
    add_data_options(cal, required=True, help="the observed trajectories the model was fitted on (as for 'fit')")
    add_system_option(cal)
    cal.add_argument(
        "--derivative", default="auto", help="how dy/dt is estimated from the states, as for 'fit' (default: auto)"
    )
    _calibration_options(cal)
    cal.add_argument("--out", help="output model file, .pt (default: rewrite --model)")
    cal.add_argument("--quiet", action="store_true", help="no progress bars")
    cal.set_defaults(func=_recalibrate)
