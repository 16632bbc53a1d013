"""The work several of the paper's figures share (:class:`Session`), and the set-ups it builds: §5.1's fit (Figs 1
and 2), §5.2's design and random set with their fits (Figs 3 and 4), §5.3's gravity designs (Figs 6 and 7).
"""

from __future__ import annotations

import functools
import numbers
import time
from dataclasses import dataclass

import torch

from .. import design as _design
from .._errors import InputError
from ..data import Trajectories, simulate
from ..design import candidates as _candidates
from ..gp import CorrectionGP
from ..learning.samples.observations import correction_samples
from ..prediction.dynamics import CorrectedODE
from ..systems import MisspecifiedSystem, paper_gravity, paper_linear
from ._setup import (
    GRAVITY_CANDIDATES,
    GRAVITY_PRIOR,
    LINEAR_GRID_SIZE,
    LINEAR_PRIOR,
    NOISE_STD,
    gravity_times,
    linear_times,
)

FINE_TIMES = 61  # plotting / scoring grid


def _generator(seed: int, tag: int) -> torch.Generator:
    """An independent stream per (seed, figure/purpose tag)."""
    return torch.Generator().manual_seed(int(seed) * 1_000_003 + int(tag))


def _true_and_known(system: MisspecifiedSystem, y0: torch.Tensor, times: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The true ``(K, T, d)`` and the known model's (misspecified) trajectories from ``y0``."""
    return simulate(system, y0, times).states, simulate(system, y0, times, known_only=True).states


# ================================================================================ §5.1 set-up (Figs 1 and 2)
@dataclass(frozen=True)
class _LinearFit:
    system: MisspecifiedSystem
    times: torch.Tensor  # (11,) observed
    fine: torch.Tensor  # (61,) plotted / scored
    y0: torch.Tensor  # (40, 2)
    train: Trajectories  # observed, T = 11
    train_fine: torch.Tensor
    train_mis_fine: torch.Tensor
    gp_paper: CorrectionGP
    gp_ml: CorrectionGP
    y_test: torch.Tensor
    test_true: torch.Tensor
    test_mis: torch.Tensor
    corrected_paper: torch.Tensor
    corrected_ml: torch.Tensor
    seconds: dict


def _linear_fit_run(
    seed: int, realization: int, *, n_train: int = 40, n_test: int = 10, progress: bool = False
) -> _LinearFit:
    system = paper_linear()
    gen = _generator(seed, 100 + realization)
    times, fine = linear_times(), linear_times(FINE_TIMES)
    sec = {}
    t0 = time.perf_counter()
    y0 = _candidates.uniform_box(n_train, system.domain, generator=gen)
    train = simulate(system, y0, times)
    samples = correction_samples(train, system, derivative="oracle", noise_std=NOISE_STD, generator=gen)
    y_test = _candidates.uniform_box(n_test, system.domain, generator=gen)
    sec["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    gp_paper = CorrectionGP(**LINEAR_PRIOR).fit(samples.inputs, samples.targets)
    sec["fit_paper"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    gp_ml = CorrectionGP().fit(samples.inputs, samples.targets, progress=progress)
    sec["fit_marginal_likelihood"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    corrected_paper = CorrectedODE(system, gp_paper).predict(y_test, fine)
    corrected_ml = CorrectedODE(system, gp_ml).predict(y_test, fine)
    sec["predict"] = time.perf_counter() - t0
    train_fine, train_mis_fine = _true_and_known(system, y0, fine)
    test_true, test_mis = _true_and_known(system, y_test, fine)
    return _LinearFit(
        system=system,
        times=times,
        fine=fine,
        y0=y0,
        train=train,
        train_fine=train_fine,
        train_mis_fine=train_mis_fine,
        gp_paper=gp_paper,
        gp_ml=gp_ml,
        y_test=y_test,
        test_true=test_true,
        test_mis=test_mis,
        corrected_paper=corrected_paper,
        corrected_ml=corrected_ml,
        seconds=sec,
    )


# =========================================== design comparisons: §5.2 (Figs 3 and 4) and §5.3 (Figs 6 and 7)
@dataclass(frozen=True)
class _Designs:
    """Designs compared on one system (Figs 3-4 and 6-7): the fits of their samples and their test predictions."""

    system: MisspecifiedSystem
    candidates: torch.Tensor  # (N, d)
    times: torch.Tensor  # (T,) observed
    fine: torch.Tensor  # (61,) plotted / scored
    prior: CorrectionGP
    plans: dict  # name -> DesignResult
    traj_obs: dict  # name -> (K, T, d) true trajectories of the picks, observed
    traj_fine: dict  # name -> (K, 61, d) the same on the fine grid
    gps: dict  # name -> CorrectionGP conditioned on the picks' samples
    y_test: torch.Tensor  # (K', d)
    test_idx: torch.Tensor | None  # (K',) indices of the test set in the candidates, or None
    test_true: torch.Tensor  # (K', 61, d)
    test_mis: torch.Tensor
    corrected: dict  # name -> (K', 61, d)


def _compare_designs(
    system: MisspecifiedSystem,
    candidates: torch.Tensor,
    plans: dict,
    prior: CorrectionGP,
    times: torch.Tensor,
    fine: torch.Tensor,
    gen: torch.Generator,
    *,
    y_test: torch.Tensor | None = None,
    n_test_unchosen: int = 0,
) -> _Designs:
    """Sample each plan's true trajectories (oracle + noise), fit the prior's fixed copy, predict a test set.

    The test set is ``y_test`` or, when it is None, ``n_test_unchosen`` random candidates no plan picked (drawn
    from ``gen`` after the samples).
    """
    traj_obs, traj_fine, gps = {}, {}, {}
    for name, plan in plans.items():
        y0 = candidates[plan.indices]
        obs = simulate(system, y0, times)
        samples = correction_samples(obs, system, derivative="oracle", noise_std=NOISE_STD, generator=gen)
        traj_obs[name] = obs.states
        traj_fine[name] = simulate(system, y0, fine).states
        gps[name] = prior.condition(samples.inputs, samples.targets)
    test_idx = None
    if y_test is None:
        chosen = set(torch.cat([p.indices for p in plans.values()]).tolist())
        free = torch.tensor([i for i in range(candidates.shape[0]) if i not in chosen])
        test_idx = free[torch.randperm(free.numel(), generator=gen)[:n_test_unchosen]]
        y_test = candidates[test_idx]
    corrected = {name: CorrectedODE(system, gp).predict(y_test, fine) for name, gp in gps.items()}
    test_true, test_mis = _true_and_known(system, y_test, fine)
    return _Designs(
        system=system,
        candidates=candidates,
        times=times,
        fine=fine,
        prior=prior,
        plans=plans,
        traj_obs=traj_obs,
        traj_fine=traj_fine,
        gps=gps,
        y_test=y_test,
        test_idx=test_idx,
        test_true=test_true,
        test_mis=test_mis,
        corrected=corrected,
    )


def _linear_design(seed: int, n_test: int = 30) -> _Designs:
    """The Fig 3/4 set-up: the K = 9 design and a random set of 9 on the 13 x 13 grid, their fits, a test set."""
    system = paper_linear()
    times = linear_times()
    candidates = _candidates.grid(system.domain, LINEAR_GRID_SIZE)
    prior = CorrectionGP(**LINEAR_PRIOR)
    gen = _generator(seed, 300)
    plans = {
        "design": _design.greedy(candidates, 9, system=system, times=times, gp=prior),
        "random": _design.random(candidates, 9, generator=gen, system=system, times=times, gp=prior),
    }
    y_test = _candidates.uniform_box(n_test, system.domain, generator=gen)
    return _compare_designs(system, candidates, plans, prior, times, linear_times(FINE_TIMES), gen, y_test=y_test)


def _gravity(seed: int, n_test: int = 5) -> _Designs:
    """The Fig 6/7 set-up; candidates and designs are those of :func:`gravity_study` with the same seed."""
    system = paper_gravity()
    candidates = _candidates.orbits(GRAVITY_CANDIDATES, generator=torch.Generator().manual_seed(seed))
    times = gravity_times()
    prior = CorrectionGP(**GRAVITY_PRIOR)
    plans = {
        "agnostic": _design.agnostic(candidates, 7, system=system, times=times, gp=prior),
        "misspecified-aided": _design.greedy(candidates, 7, system=system, times=times, gp=prior),
    }
    return _compare_designs(
        system,
        candidates,
        plans,
        prior,
        times,
        gravity_times(FINE_TIMES),
        _generator(seed, 600),
        n_test_unchosen=n_test,
    )


# =============================================================================================== shared work
class Session:
    """The work several figures share, for one seed: built on first use, kept as long as this object lives.

    * :attr:`linear_fit`: realization 0 of §5.1 (Figs 1 and 2);
    * :attr:`linear_design`: the K = 9 design and random set of §5.2 with their fits (Figs 3 and 4);
    * :attr:`gravity`: the §5.3 candidates, designs and fits (Figs 6 and 7).

    :func:`~torchmisspec.paper.figures.reproduce` makes one per run and passes it to every figure
    (``figure_N(out, session=...)``); a figure called without one makes its own. The fitted models live in this
    object, not in the module.
    """

    def __init__(self, seed: int = 0) -> None:
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
            raise InputError(f"seed: expected an integer, got {seed!r} ({type(seed).__name__})")
        self.seed = int(seed)

    @functools.cached_property
    def linear_fit(self) -> _LinearFit:
        return _linear_fit_run(self.seed, 0)

    @functools.cached_property
    def linear_design(self) -> _Designs:
        return _linear_design(self.seed)

    @functools.cached_property
    def gravity(self) -> _Designs:
        return _gravity(self.seed)

    def __repr__(self) -> str:
        built = [name for name in ("linear_fit", "linear_design", "gravity") if name in self.__dict__]
        return f"Session(seed={self.seed}, built={built})"


def _session(session: Session | None, seed: int) -> Session:
    """``session``, checked against ``seed``, or a new one for ``seed``."""
    if session is None:
        return Session(seed)
    if not isinstance(session, Session):
        raise InputError(f"session: expected a Session or None, got {type(session).__name__}")
    if session.seed != seed:
        raise InputError(f"session: expected a Session for seed={seed} (the seed argument), got seed={session.seed}")
    return session
