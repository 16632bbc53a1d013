#!/usr/bin/env python
"""Regenerate the figures of the paper's §5 and the numbers behind them (logic: torchmisspec.paper.figures).

    python scripts/reproduce_paper.py --all                   # all eight figures into reproduction-output/
    python scripts/reproduce_paper.py --figure 1 --figure 2   # some figures
    python scripts/reproduce_paper.py --all --smoke           # tiny sizes, checks everything runs (CI)
    python scripts/reproduce_paper.py --all --out DIR --seed 3 --quiet
    python scripts/reproduce_paper.py --all --threads 0       # torch's default thread count (default: 1)

Writes figN.png (and a few figN_<panel>.png) and results.json (figure -> measured numbers, timings, smoke flag,
realization counts) into --out, and prints each figure's time and key numbers unless --quiet.
"""

from __future__ import annotations

import argparse
import sys
import time

from torchmisspec.paper.figures import FIGURES, reproduce


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="reproduce_paper.py",
        description="Regenerate the figures of paper §5 (Numerical Experiments) with the numbers behind them.",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--figure",
        type=int,
        action="append",
        choices=sorted(FIGURES),
        metavar="N",
        help="figure number 1-8 (repeatable)",
    )
    which.add_argument("--all", action="store_true", help="all eight figures")
    p.add_argument("--out", default="reproduction-output", help="output folder (default: %(default)s)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes: checks that everything runs, in seconds")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads (default: %(default)s; the problems are small, one thread is fastest on a "
        "shared machine; 0 keeps torch's default)",
    )
    return p


def _summary(results: dict) -> str:
    f, lines = results["figures"], []

    def ratio_line(data: dict, key: str) -> str:
        r = data["ratios"][key]
        cells = ", ".join(f"K={k}: {m:.3f}±{s:.3f}" for k, m, s in zip(data["ks"], r["mean"], r["stderr"], strict=True))
        return f"  {key}: {cells}"

    for key, secs in results["seconds"].items():
        if key == "total":
            continue
        d = f[key]
        lines.append(f"{key}: {secs:.1f} s, files {', '.join(d.get('files', []))}")
        if key == "fig1":
            p = d["fits"]["paper_prior"]
            r = d["rmse_ratio_over_realizations"]["paper_prior"]
            lines.append(
                f"  test RMSE corrected/misspecified {p['rmse_ratio']:.3f} (paper prior); over {r['n']} "
                f"realizations {r['mean']:.3f}±{r['stderr']:.3f}"
            )
        elif key == "fig2":
            lines.append(
                f"  integrated error {d['integrated_error']['paper_prior']:.4g} (energy of F "
                f"{d['energy_of_F']:.4g}); far/near traces {d['near_vs_far']['far_over_near']:.2f}"
            )
        elif key == "fig3":
            lines.append(
                f"  design/random: test RMSE {d['design_over_random']['test_rmse']:.3f}, integrated error "
                f"{d['design_over_random']['integrated_error']:.3f}, information gain "
                f"{d['design']['information_gain_nats']:.2f} vs {d['random']['information_gain_nats']:.2f} "
                "nats"
            )
        elif key == "fig4":
            lines.append(
                f"  per-component integrated |error| design/random: "
                f"{', '.join(f'{v:.3f}' for v in d['design_over_random'])}"
            )
        elif key == "fig5":
            lines += [ratio_line(d, "design/random"), ratio_line(d, "data-driven/design")]
        elif key == "fig6":
            lines.append(
                f"  test RMSE: misspecified {d['misspecified_test_rmse']:.3g}, agnostic "
                f"{d['agnostic']['test_rmse_corrected']:.3g}, aided "
                f"{d['misspecified-aided']['test_rmse_corrected']:.3g}"
            )
        elif key == "fig7":
            lines.append(
                f"  MSE over D: agnostic {d['agnostic']['mse_over_D']:.3g}, aided "
                f"{d['misspecified-aided']['mse_over_D']:.3g} (ratio "
                f"{d['aided_over_agnostic_mse_over_D']:.3f})"
            )
        elif key == "fig8":
            lines.append(ratio_line(d, "misspecified-aided/agnostic"))
    lines.append(
        f"total {results['seconds'].get('total', 0.0):.1f} s; realizations {results['realizations']}; "
        f"smoke={results['smoke']}"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    figures = sorted(FIGURES) if args.all else args.figure
    t0 = time.perf_counter()
    if args.threads < 0:
        _parser().error(f"argument --threads: expected an integer >= 0, got {args.threads}")
    results = reproduce(
        figures, args.out, smoke=args.smoke, seed=args.seed, progress=not args.quiet, threads=args.threads or None
    )
    if not args.quiet:
        print(_summary(results))
        print(f"wrote {args.out}/results.json in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
