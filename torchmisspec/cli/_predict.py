"""``torchmisspec predict``: trajectories from new initial conditions with calibrated bands, as a CSV and a figure."""

from __future__ import annotations

import argparse
import sys
import warnings

from .._errors import InputError
from ._common import (
    add_column_options,
    add_system_option,
    check_names,
    check_output,
    input_columns,
    known_state_names,
    load_model,
    read_controls,
    read_states,
    seed,
    write_csv,
    written,
)
from ._tables import parse_times

__all__ = ["add_predict"]

MAX_FIGURE_ROWS = 6  # initial conditions drawn in the figure (one row of panels each)


def _predict(args: argparse.Namespace) -> int:
    import torch

    from ..prediction.dynamics import CorrectedODE

    out = check_output(args.out, (".csv",))
    figure = None if args.figure is None else check_output(args.figure, (".png",), "--figure")
    system, gp, times, y0, names, labels, readout, controls = _read_inputs(args)
    model = CorrectedODE(system, gp)
    calibrated = model.calibration_ is not None
    with warnings.catch_warnings():
        # the command says itself, once, whether the bands are calibrated
        warnings.filterwarnings("ignore", message=".*not calibrated.*")
        post = model.posterior(
            y0,
            times,
            num_samples=args.samples,
            generator=torch.Generator().manual_seed(args.seed),
            scale=None,
            controls=controls,
        )
    if args.measurements:  # the band that new measurements fall in: the noise the fit found, in its own space
        post = post.measured(gp.noise_, gp.noise_scale_, generator=torch.Generator().manual_seed(args.seed + 1))
    lower, upper = post.interval(args.level)
    header, rows = _table(post, lower, upper, times.tolist(), names, labels, readout, args)
    write_csv(out, header, rows)
    print(_summary(args, model, post, (lower, upper), times.numel(), out))
    if not calibrated:
        print(
            f"torchmisspec predict: warning: the model's bands are not calibrated (with few experiments they are "
            f"usually too narrow); run 'torchmisspec calibrate --model {args.model} --data ...' first",
            file=sys.stderr,
        )
    below = below_zero(gp, lower, times, names)
    if below:
        print(f"torchmisspec predict: warning: {below}", file=sys.stderr)
    if figure is not None:
        _figure(post, figure, names, labels, args)
        shown = min(y0.shape[0], MAX_FIGURE_ROWS)
        print(f"figure of {'the first ' + str(shown) if shown < y0.shape[0] else shown} initial condition(s): {figure}")
    return 0


def _read_inputs(args: argparse.Namespace) -> tuple:
    """``(system, gp, times, y0, names, labels, readout, controls)``: the command's inputs read and checked, every
    cheap check before the model file is read and the work begins."""
    from ..systems import load_system

    if not 0 < args.level < 1:
        raise InputError(f"--level: expected a band's coverage in (0, 1), got {args.level}")
    if args.samples < 2:
        raise InputError(f"--samples: expected at least 2 posterior draws for a band, got {args.samples}")
    times = parse_times(args.times)
    system = load_system(args.system)
    input_columns(args, system)  # checked before the work (read with --controls)
    if system.num_controls and args.controls is None:
        raise InputError(
            f"--system: '{system.name}' has inputs u(t) {list(system.control_names)}; pass their profiles for the "
            "initial conditions with --controls profiles.csv (columns: experiment, time, the inputs)"
        )
    if args.controls is not None and not system.num_controls:
        raise InputError(
            f"--controls: expected none, system '{system.name}' has no inputs u(t), got {args.controls!r}; drop it"
        )
    gp = load_model(args.model, system)
    if args.measurements and getattr(gp, "noise_scale_", None) is None:
        raise InputError(
            f"--measurements: expected a model file written by 'fit' with its measurement noise recorded, got "
            f"{args.model} without it (written by an older version, or a model not fitted to data); refit it with "
            "'torchmisspec fit', or drop --measurements for the band of the states themselves"
        )
    y0, names, labels = read_states(args.initial, "--initial", args, system, known_state_names(system, gp))
    names = check_names(gp, names, system, "--initial")
    readout = None
    if args.readout:  # checked before the work
        from ..data import Readout

        readout = Readout.parse(args.readout, names)
    labels = labels if labels is not None else [str(b) for b in range(y0.shape[0])]
    controls = None if args.controls is None else read_controls(args.controls, args, system, labels)
    return system, gp, times, y0, names, labels, readout, controls


def _table(post, lower, upper, times: list[float], names, labels, readout, args) -> tuple[list, list]:
    """``(header, rows)`` of the prediction's CSV: one row per initial condition and time, the mean and the band of
    every state (and of every reading of ``readout``)."""
    mean = post.mean_path
    B, d = mean.shape[0], mean.shape[-1]
    rows = []
    for b in range(B):
        for i, t in enumerate(times):
            values = []
            for j in range(d):
                values += [float(mean[b, i, j]), float(lower[b, i, j]), float(upper[b, i, j])]
            rows.append([labels[b], t, *values])
    header = [args.experiment_column or "experiment", args.time_column]
    for name in names:
        header += [f"{name}_mean", f"{name}_lower", f"{name}_upper"]
    if readout is not None:  # the readings' bands too: the quantiles of the draws read out
        read = post.read(readout)
        low, high = read.interval(args.level)
        for row, (b, i) in zip(rows, ((b, i) for b in range(B) for i in range(len(times))), strict=True):
            for r in range(low.shape[-1]):
                row += [float(read.mean_path[b, i, r]), float(low[b, i, r]), float(high[b, i, r])]
        for name in read.state_names:
            header += [f"{name}_mean", f"{name}_lower", f"{name}_upper"]
    return header, rows


def below_zero(gp, lower, times, names) -> str:
    """What to say where the band's lower edge ``lower (B, T, d)`` goes below 0 for a state the fit's noise model
    measures as positive (relative or count noise: a concentration, a count); ``""`` where it does not. On nlme's
    Indometh (one subject, a one-compartment bolus written for the trial) the band reached -0.013 mcg/mL past the
    last measurement: F's draws near the smallest concentrations measured."""
    from ..noise import Additive, NoiseModel
    from ..prediction._flags import first_flagged

    noise = getattr(gp, "noise_", None)
    if not isinstance(noise, NoiseModel) or isinstance(noise, Additive):
        return ""
    found = [f"{name} {since}" for _, name, since in first_flagged(names, times, (lower < 0).any(0))]
    if not found:
        return ""
    return (
        f"the band's lower edge goes below 0 ({'; '.join(found)}) for states measured positive (noise "
        f"'{noise.name}'): the draws of F (or of G's parameters) there go beyond what the data pin down; read that "
        "edge as 0, and the band as the data's only where they were measured"
    )


def _summary(args: argparse.Namespace, model, post, interval, num_times: int, out) -> str:
    """The line that says what was predicted: the band (calibrated or not), and the draws that left the region, the
    band entries left empty and the mean paths that stop early, where any."""
    import torch

    lower, upper = interval
    gp = model.gp
    missing = int((torch.isnan(lower) | torch.isnan(upper)).sum())  # too few draws remain there
    stopped = int(model.incomplete.sum()) if model.incomplete is not None else 0  # mean paths that stop early
    left = int((post.fraction_remaining < 1).sum())
    of = f" of new measurements ({gp.noise_.name} noise, scale {_scales(gp.noise_scale_)})" if args.measurements else ""
    band = f"the central {args.level:.0%} band{of}" + (
        f", calibrated (scale {model.calibration_.scale:.3g}, saved in {args.model})"
        if model.calibration_ is not None
        else ", NOT calibrated: the GP's own bands"
    )
    return (
        f"predicted {lower.shape[0]} trajectories x {num_times} times with {band} from {args.samples} posterior "
        f"draws; written to {out}"
        + (
            f"; draws of {left} initial condition(s) left the region (at least "
            f"{float(post.fraction_remaining.min()):.0%} remain): their bands are of the draws that remain"
            if left
            else ""
        )
        + (f"; {missing} band entries are empty (NaN: too few draws remain there)" if missing else "")
        + (f"; {stopped} mean path(s) stop early (NaN from there)" if stopped else "")
    )


def _figure(post, path, names, labels, args: argparse.Namespace) -> None:
    """One row of panels (one per state) for each of the first initial conditions, with the band and its legend."""
    from matplotlib.figure import Figure

    from ..plotting import plot_prediction_bands

    n = min(post.samples.shape[1], MAX_FIGURE_ROWS)
    d = post.samples.shape[-1]
    fig = Figure(figsize=(4.0 * d, 2.8 * n), layout="constrained")
    axes = fig.subplots(n, d, squeeze=False)
    for b in range(n):
        plot_prediction_bands(
            post,
            index=b,
            levels=(args.level,),
            component_labels=names,
            axes=list(axes[b]),
            title=f"{args.experiment_column or 'experiment'} {labels[b]}"
            + (": bands of new measurements" if args.measurements else ""),
            legend=b == 0,
        )
        for ax in axes[b]:
            ax.set_xlabel(args.time_column)
    with written(path) as tmp:
        fig.savefig(tmp, dpi=100)


def add_predict(sub) -> None:
    pre = sub.add_parser(
        "predict",
        help="predict trajectories from new initial conditions, with uncertainty bands (a CSV and a figure)",
        description="Integrate the corrected model (G + the correction's posterior mean) from each initial condition, "
        "and posterior draws of the correction for the bands (CorrectedODE.posterior), calibrated when the model file "
        "holds a calibration (written by 'fit' or 'calibrate'). Writes one row per initial condition and time: "
        "experiment, time, and <state>_mean, <state>_lower, <state>_upper for every state (and for every --readout, "
        "the band of what it reads).",
    )
    pre.add_argument("--model", required=True, help="the model file written by 'fit' (or 'calibrate')")
    add_system_option(pre)
    pre.add_argument(
        "--initial",
        required=True,
        help="initial conditions, one per row: a CSV/TSV/TXT with a header of state names (read with "
        "--state-columns; an --experiment-column labels the rows), or a table without header, .npy or .npz, in "
        "the system's order",
    )
    pre.add_argument(
        "--times", required=True, help="output times: 'start:stop:count', a comma list, or a file of times"
    )
    pre.add_argument(
        "--controls",
        help="for a system with inputs u(t): their profiles, a CSV/TSV/TXT with the --experiment-column (labels as "
        "in --initial; without it, one profile for all), the --time-column and one column per input (named as the "
        "system's controls, or --input-columns), each experiment's rows the profile's samples (--input-kind)",
    )
    add_column_options(pre)
    pre.add_argument("--level", type=float, default=0.9, help="the central band written (default: %(default)s)")
    pre.add_argument("--samples", type=int, default=64, help="posterior draws for the bands (default: %(default)s)")
    pre.add_argument("--seed", type=seed, default=0, help="seed of the draws (default: %(default)s)")
    pre.add_argument("--out", default="prediction.csv", help="output table, .csv (default: %(default)s)")
    pre.add_argument(
        "--figure", help=f"also draw the prediction and band (the first {MAX_FIGURE_ROWS} initial conditions), .png"
    )
    pre.add_argument(
        "--measurements",
        action="store_true",
        help="bands of new measurements: the states' band with the measurement noise the fit found added (its noise "
        "model and scale, saved in the model file); default: the band of the states themselves",
    )
    pre.add_argument("--quiet", action="store_true", help="no progress output (prediction has no progress bar yet)")
    pre.set_defaults(func=_predict)


def _scales(scale) -> str:
    """Each component's noise scale, short (``-`` for one never measured)."""
    return ", ".join("-" if v != v else f"{v:.3g}" for v in scale.tolist())
