"""Calibration from one experiment on its time pieces, on the one-trajectory protocols (issue 41).

For each seed of a protocol of ``scripts/study_one_trajectory.py``: the default fit, the 90 % band's coverage of the
true trajectory over each half of the horizon with the GP's own bands, ``CorrectedODE.calibrate`` on the one
trajectory (held out: pieces of its time), its scale and seconds, and the coverage again with the calibrated scale.

Usage::

    python scripts/probe_one_trajectory_calibration.py --protocol gpode_van_der_pol --seeds 6
"""

from __future__ import annotations

import argparse
import time
import warnings

import torchmisspec as tms
from torchmisspec.paper import study_one_trajectory as protocols


def _halves(rec: dict) -> str:
    return (
        "/".join(f"{v:.2f}" for v in rec["band_covers_truth_halves"]) + f" (finite {rec['band_finite_fraction']:.2f})"
    )


def probe(name: str, seed: int) -> str:
    """One seed's line: the calibration's scale and time, the coverage halves before and after."""
    data = protocols.make_data(name, seed)
    traj = tms.Trajectories(data["times"], data["noisy"].unsqueeze(0), state_names=["x", "y"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = tms.CorrectedODE(data["system"], tms.fit_correction(traj, data["system"], progress=False))
        cfg, before, after = {"num_samples": 64, "level": 0.9}, {}, {}
        protocols.band(data, model, cfg, before)
        t0 = time.perf_counter()
        cal = model.calibrate(traj, progress=False)  # its default draws (seed 0)
        seconds = time.perf_counter() - t0
        protocols.band(data, model, cfg, after)
    return (
        f"{name} seed {seed}: calibrate {seconds:.1f} s, scale {cal.scale:.3g} (held-out coverage at 1: "
        f"{cal.coverage_at_one:.2f}) | truth covered, halves: GP's own {_halves(before)}, calibrated {_halves(after)}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--protocol", default="gpode_van_der_pol", choices=sorted(protocols.PROTOCOLS))
    parser.add_argument("--seeds", type=int, default=6, help="seeds 0 .. seeds - 1")
    args = parser.parse_args(argv)
    for seed in range(args.seeds):
        print(probe(args.protocol, seed), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
