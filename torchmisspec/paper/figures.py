"""Regenerate the eight figures of the paper's §5 ("Numerical Experiments"), with the numbers behind each one.

One function per figure, ``figure_N(out, *, smoke=False, seed=0, progress=False, session=None) -> dict``: it writes
``figN.png`` (and, where a figure has panels worth reading alone, ``figN_<panel>.png``) into ``out`` and returns a
JSON-serialisable dict of what the package measured for that figure (nothing is typed in: every number comes from
the run). :func:`reproduce` runs a list of figures and writes ``results.json`` (figure -> numbers, timings, the
smoke flag and the realization counts). ``scripts/reproduce_paper.py`` is the command-line front end.

What each figure reproduces:

* Fig 1 (§5.1): 40 random initial conditions in D = [-1, 1]^2, T = 11 on [0, 6], oracle samples of F with noise std
  1e-2; the correction GP with the paper's fixed RBF prior (l = 1, output scale 4e-5, noise 1e-4; plotted) and by
  marginal likelihood; training (left) and test (right) trajectories; test RMSE ratios over realizations.
* Fig 2 (§5.1): `||F_hat - F||_2` over D with the training traces; error near vs far from the traces.
* Fig 3 (§5.2): 13 x 13 candidate grid, the K = 9 lazy-greedy design and 9 random picks with their trajectories;
  predictions of both corrected models on a test set.
* Fig 4 (§5.2): `|F_hat_i - F_i|` maps, random (top) vs design (bottom).
* Fig 5 (§5.2): integrated error vs K for design / random / data-driven over realizations
  (:func:`~torchmisspec.paper.studies.linear_study`).
* Fig 6 (§5.3): gravity; 300 candidates, the masses, the agnostic and misspecified-aided designs of size 7 with
  their trajectories; predictions on a random test set.
* Fig 7 (§5.3): `||F_hat_{3,4} - F_{3,4}||_2` maps of both designs over a box larger than D (D dashed).
* Fig 8 (§5.3): mean squared error over D vs K over noise realizations
  (:func:`~torchmisspec.paper.studies.gravity_study`).

Choices the paper leaves open are those of the package (see :func:`~torchmisspec.systems.paper_gravity` for the
gravity domain D and :func:`~torchmisspec.design.candidates.orbits` for the candidate set). Trajectories are
*plotted and scored* on a finer time grid (61 times) than the one observed for training (T = 11 or 20), so the
test RMSEs measure the whole predicted paths. Information gains are in nats of a real Gaussian (half the paper's
complex-convention numbers; see :mod:`torchmisspec.design`).

Work is shared between figures through a :class:`Session` (the Fig 1 fit serves Fig 2, the Fig 3 designs serve
Fig 4, the gravity set-up serves Figs 6 and 7): :func:`reproduce` makes one per run and passes it to every figure;
a figure called without one builds what it needs. Nothing is cached at module level.

The figures are grouped by section in private modules: ``_figs_linear`` (§5.1, Figs 1-2), ``_figs_design`` (§5.2,
Figs 3-5) and ``_figs_gravity`` (§5.3, Figs 6-8); the work they share in ``_session`` (:class:`Session`) and the
pieces they share in ``_measures``; this module runs them (:func:`reproduce`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._errors import InputError
from .._validation import check_positive_int
from ._figs_design import figure_3, figure_4, figure_5
from ._figs_gravity import figure_6, figure_7, figure_8
from ._figs_linear import figure_1, figure_2
from ._session import FINE_TIMES as FINE_TIMES  # not in __all__, importable here as before
from ._session import Session
from ._setup import GRAVITY_PRIOR, LINEAR_PRIOR, NOISE_STD

__all__ = [
    "FIGURES",
    "Session",
    "LINEAR_PRIOR",
    "GRAVITY_PRIOR",
    "NOISE_STD",
    "figure_1",
    "figure_2",
    "figure_3",
    "figure_4",
    "figure_5",
    "figure_6",
    "figure_7",
    "figure_8",
    "reproduce",
]


def _jsonable(x: Any) -> Any:
    """Tensors, arrays and numpy scalars -> lists and Python numbers, recursively."""
    if isinstance(x, torch.Tensor):
        return _jsonable(x.detach().cpu().tolist())
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


# ==================================================================================================== driver
FIGURES: dict[int, Callable[..., dict]] = {
    1: figure_1,
    2: figure_2,
    3: figure_3,
    4: figure_4,
    5: figure_5,
    6: figure_6,
    7: figure_7,
    8: figure_8,
}


def reproduce(
    figures: Iterable[int],
    out: str | Path = "reproduction-output",
    *,
    smoke: bool = False,
    seed: int = 0,
    progress: bool = False,
    threads: int | None = 1,
) -> dict:
    """Run the given figures (numbers 1-8) into ``out`` and write ``out/results.json``.

    ``results.json`` holds ``{"smoke", "seed", "figures": {"fig1": numbers, ...}, "seconds": {"fig1": s, ...,
    "total": s}, "realizations": {"fig1": n, "fig5": n, "fig8": n}, "torch_threads"}``; it is rewritten after
    every figure, so a long run leaves the finished figures' numbers behind. Returns the same dict.

    ``threads``: torch intra-op threads during the run (restored afterwards; ``None`` leaves torch's setting).
    The matrices here are small (at most a few hundred samples), so one thread loses nothing, and it keeps the
    timings stable on a shared machine: with every core's thread spinning, a busy neighbour made single
    factorizations of a 440 x 440 matrix take 100x longer.
    """
    if threads is not None:
        threads = check_positive_int(threads, "threads")
    try:
        numbers = [int(n) for n in figures]
    except (TypeError, ValueError) as exc:
        raise InputError(f"figures: expected figure numbers in 1..8, got {figures!r}") from exc
    bad = [n for n in numbers if n not in FIGURES]
    if not numbers or bad:
        raise InputError(f"figures: expected at least one figure number in 1..8, got {numbers}")
    numbers = sorted(set(numbers))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, Any] = {
        "smoke": bool(smoke),
        "seed": int(seed),
        "figures": {},
        "seconds": {},
        "realizations": {},
    }
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _run(numbers, out, results, smoke=smoke, session=Session(seed), progress=progress)
    finally:
        torch.set_num_threads(previous)


def _run(numbers: list[int], out: Path, results: dict, *, smoke: bool, session: Session, progress: bool) -> dict:
    results["torch_threads"] = torch.get_num_threads()
    say = None
    if progress:
        from tqdm.auto import tqdm

        say = tqdm.write
    start = time.perf_counter()
    for n in numbers:
        key = f"fig{n}"
        if say is not None:
            say(f"Figure {n}: running ...")
        t0 = time.perf_counter()
        nums = _jsonable(FIGURES[n](out, smoke=smoke, seed=session.seed, progress=progress, session=session))
        results["seconds"][key] = time.perf_counter() - t0
        results["figures"][key] = nums
        if "realizations" in nums:
            results["realizations"][key] = int(nums["realizations"])
        results["seconds"].pop("total", None)  # keep "total" last
        results["seconds"]["total"] = time.perf_counter() - start
        (out / "results.json").write_text(json.dumps(results, indent=2))
        if say is not None:
            say(f"Figure {n}: done in {results['seconds'][key]:.1f} s -> {', '.join(nums.get('files', []))}")
    return results
