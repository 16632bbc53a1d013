"""``torchmisspec predict``: trajectories from new initial conditions with calibrated bands, as a CSV and a figure."""

from __future__ import annotations

import argparse
import warnings

from .._errors import InputError, TorchMisspecWarning
from ._common import add_system_option, check_output, load_model, parse_times, read_table, write_csv

__all__ = ["add_predict"]


def _predict(args: argparse.Namespace) -> int:
    import torch

    from ..dynamics import CorrectedODE
    from ..systems import load_system

    out = check_output(args.out, (".csv",))
    figure = None if args.figure is None else check_output(args.figure, (".png",), "--figure")
    if not 0 < args.level < 1:
        raise InputError(f"--level: expected a band's coverage in (0, 1), got {args.level}")
    if args.samples < 2:
        raise InputError(f"--samples: expected at least 2 posterior draws for a band, got {args.samples}")
    system = load_system(args.system)
    gp = load_model(args.model, system)
    table, header = read_table(args.initial, "initial")
    y0 = torch.as_tensor(table, dtype=torch.float64)
    y0 = y0.unsqueeze(0) if y0.dim() == 1 else y0
    if y0.shape[-1] != system.state_dim:
        raise InputError(
            f"--initial: expected {system.state_dim} states per row (system '{system.name}'), got rows of "
            f"{y0.shape[-1]} in {args.initial}"
        )
    names = header if header is not None and len(header) == system.state_dim else [f"y{j}" for j in range(y0.shape[-1])]
    times = parse_times(args.times)
    model = CorrectedODE(system, gp)
    calibrated = model.calibration_ is not None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", TorchMisspecWarning)
        post = model.posterior(
            y0, times, num_samples=args.samples, generator=torch.Generator().manual_seed(args.seed), scale=None
        )
    for w in caught:  # the library's warnings reach the user as one line each
        if calibrated or "not calibrated" not in str(w.message):
            print(f"torchmisspec predict: warning: {w.message}")
    lower, upper = post.interval(args.level)
    mean = post.mean_path
    rows = []
    for b in range(y0.shape[0]):
        for i, t in enumerate(times.tolist()):
            values = []
            for j in range(system.state_dim):
                values += [float(mean[b, i, j]), float(lower[b, i, j]), float(upper[b, i, j])]
            rows.append([b, t, *values])
    header_out = ["initial", args.time_name]
    for name in names:
        header_out += [name, f"{name}_lower", f"{name}_upper"]
    write_csv(out, header_out, rows)
    unbounded = int((~torch.isfinite(lower) | ~torch.isfinite(upper)).sum())
    band = f"the central {args.level:.0%} band" + (
        f", calibrated (scale {model.calibration_.scale:.3g})" if calibrated else ", NOT calibrated: the GP's own bands"
    )
    print(
        f"predicted {y0.shape[0]} trajectories x {times.numel()} times with {band} from {args.samples} posterior "
        f"draws; written to {out}"
        + (f"; {unbounded} band entries are unbounded (diverging draws)" if unbounded else "")
    )
    if not calibrated:
        print(
            "torchmisspec predict: warning: the model's bands are not calibrated (with few experiments they are "
            "usually too narrow); run 'torchmisspec calibrate' on its data first"
        )
    if figure is not None:
        from ..plotting import plot_prediction_bands

        fig = plot_prediction_bands(post, index=0, levels=(args.level,), component_labels=names, title="initial 0")
        for ax in fig.axes:
            ax.set_xlabel(args.time_name)
        fig.savefig(figure, dpi=100)
        print(f"figure of initial condition 0: {figure}")
    return 0


def add_predict(sub) -> None:
    pre = sub.add_parser(
        "predict",
        help="predict trajectories from new initial conditions, with uncertainty bands (a CSV and a figure)",
        description="Integrate the corrected model (G + the correction's posterior mean) from each initial condition, "
        "and posterior draws of the correction for the bands (CorrectedODE.posterior), calibrated when the model file "
        "holds a calibration. Writes one row per initial condition and time: the prediction and the band's lower and "
        "upper ends for every state.",
    )
    pre.add_argument("--model", required=True, help="the model file written by 'fit' (or 'calibrate')")
    add_system_option(pre)
    pre.add_argument(
        "--initial",
        required=True,
        help="initial conditions, one per row: CSV/TSV/TXT with an optional header of state names (used in the "
        "output), .npy or .npz",
    )
    pre.add_argument("--times", required=True, help="output times: 'start:stop:count' or a comma list")
    pre.add_argument("--time-name", default="time", help="name of the time column written (default: %(default)s)")
    pre.add_argument("--level", type=float, default=0.9, help="the central band written (default: %(default)s)")
    pre.add_argument("--samples", type=int, default=64, help="posterior draws for the bands (default: %(default)s)")
    pre.add_argument("--seed", type=int, default=0, help="seed of the draws (default: %(default)s)")
    pre.add_argument("--out", default="prediction.csv", help="output table, .csv (default: %(default)s)")
    pre.add_argument("--figure", help="also draw the first initial condition's prediction and band, .png")
    pre.add_argument("--quiet", action="store_true", help="no progress bars")
    pre.set_defaults(func=_predict)
