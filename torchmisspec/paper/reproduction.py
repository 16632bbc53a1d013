"""The short report of a reproduction of the paper's figures (:func:`torchmisspec.paper.figures.reproduce`), as
``scripts/reproduce_paper.py`` prints it."""

from __future__ import annotations


def summary(results: dict) -> str:
    """What ``scripts/reproduce_paper.py`` prints after a run: each figure's time, files and key numbers, from the
    results of :func:`torchmisspec.paper.figures.reproduce`."""
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
