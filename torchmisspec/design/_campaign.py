"""The design loop: ask for the next experiments, tell what was measured, refit, repeat (sequential design).

A :class:`Campaign` holds the candidate initial conditions, the observation times, the prior and everything measured
so far. ``ask(k)`` designs the next batch greedily *given the data* (gains conditioned on every sample collected,
proxies by default the corrected model's once there are data; data read through a :class:`~torchmisspec.Readout`:
designed by :class:`~torchmisspec.design.ReadoutCriterion`); ``tell(trajectories)`` adds the measured experiments
and refits: started from :func:`~torchmisspec.fit_correction`'s result, by that fit's
:class:`~torchmisspec.Pipeline` on every experiment (one way to learn, the same choice of model; an experiment held
already is not added again); otherwise the samples are added and the GP refitted (hyperparameters by marginal
likelihood once the data hold ``refit_after`` samples, the prior's fixed values before). ``history`` records every
round; ``save`` / ``load`` write and read the whole campaign (tensors and plain values only, never code).

For a system with inputs u(t), a candidate experiment is an initial state *and* an input profile: the campaign takes
``controls`` (one profile per candidate), ``ask`` returns the states with their profiles, and ``tell`` matches each
told experiment to a pending ask by its first state and its profile.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch

from .._errors import InputError, ShapeError, TorchMisspecError
from .._validation import check_domain, check_path, check_positive_int, check_real, check_writable, writing
from ..data import Trajectories
from ..data._join import known_experiments
from ..gp import CorrectionGP, _persistence
from ..learning.pipeline import Pipeline
from ..learning.samples.observations import correction_samples
from ..metrics import correction_error
from ..parallel import check_executor
from ..systems import MisspecifiedSystem
from . import _campaign_data as plain
from ._common import check_candidates, check_system, check_times
from ._domain import CRITERIA
from ._greedy import greedy
from ._options import DomainCriterion, Proxy
from ._proxy import PROXIES
from ._readings import ReadoutCriterion, campaign_criterion

__all__ = ["Campaign"]

FORMAT = "torchmisspec.Campaign"
VERSION = 1
MATCH_TOL = 1e-9  # relative tolerance for matching a told initial condition to an asked candidate
# a measured first state (noisy) matches the nearest pending ask within this fraction of the candidates' range per
# coordinate, when no pending ask matches exactly and every other pending ask is at least twice as far
NEAR_TOL = 0.1


class Campaign:
    """Sequential experimental design: ``ask`` for experiments, run them, ``tell`` the results, repeat.

    Args:
        system: the misspecified system (known model, correction inputs/outputs, domain).
        candidates: ``(N, d)`` candidate initial conditions.
        times: ``(T,)`` observation times of every experiment (the first is the initial condition's).
        gp: a :class:`~torchmisspec.CorrectionGP`, not modified: a prior whose hyperparameters are set (e.g.
            :meth:`CorrectionGP.prior <torchmisspec.CorrectionGP.prior>`) to start without data, or a fitted GP to
            start from the samples it was fitted on: the first ``ask`` is then conditioned on them. A result of
            :func:`~torchmisspec.fit_correction` also brings its trajectories (``data``) and its
            :class:`~torchmisspec.Pipeline` (``pipeline``): ``tell`` then refits with that pipeline on every
            experiment (see :meth:`tell`).
            Any model the package fits works (per-output kernels, feature kernels, per-sample noise).
        criterion: ``"information"`` (the paper's) or ``"domain"`` (variance of F over D), see
            :func:`~torchmisspec.design.greedy`.
        proxy: ``"known"`` or ``"corrected"``; default ``"corrected"`` once there are data, ``"known"`` before.
        domain: ``criterion="domain"`` only: the box D, as for :func:`~torchmisspec.design.greedy`.
        domain_size: ``criterion="domain"`` only: quadrature nodes per axis, as for
            :func:`~torchmisspec.design.greedy`.
        derivative: how ``tell`` turns states into correction samples (:func:`~torchmisspec.correction_samples`):
            ``"auto"`` for measured states; ``"oracle"`` (exact derivatives + ``noise_std``) for simulations.
        noise_std: noise added to the samples (``"oracle"``: the observation model's noise).
        refit_after: learn the hyperparameters by marginal likelihood once the data hold at least this many samples
            (default ``4 T``); before, the prior's values are kept and the GP is only conditioned. ``0`` disables
            learning (the prior is kept throughout).
        pilot: the first ``pilot`` experiments are drawn at random among the candidates (a pilot batch to learn
            hyperparameters from before designing); 0 designs from the first ask on.
        seed: seeds the pilot draws and the sample noise of ``tell``.
        executor: a ``concurrent.futures.Executor`` for the designs' proxy trajectories (see
            :func:`~torchmisspec.design.greedy`), or ``None``; not saved: set ``campaign.executor`` after ``load``.

    Attributes:
        gp: the current model: the prior before any data, then the GP fitted on every sample.
        data: every measured experiment (a :class:`~torchmisspec.Trajectories`) for a campaign started from
            :func:`~torchmisspec.fit_correction`'s result, else ``None``; ``pipeline`` that fit's
            :class:`~torchmisspec.Pipeline`.
        history: one dictionary per ``ask`` and per ``tell`` (plain values: picks, gains, hyperparameters, the error of
            the correction over the domain when the system carries its true F, notes).
    """

    def __init__(
        self,
        system: MisspecifiedSystem,
        candidates,
        times,
        gp: CorrectionGP,
        *,
        criterion: str = "information",
        proxy: str | None = None,
        domain=None,
        domain_size: int | None = None,
        derivative: str = "auto",
        noise_std: float = 0.0,
        refit_after: int | None = None,
        pilot: int = 0,
        seed: int = 0,
        controls=None,
        executor=None,
    ) -> None:
        self.system = check_system(system, controls, with_controls=True)
        self.executor = check_executor(executor)
        if system.parameters is not None and getattr(gp, "parameters_", None) is None:
            raise InputError(
                f"system: '{system.name}' has uncertain parameters {list(system.parameters.names)}, and gp holds no "
                "estimate of them; start the campaign from fit_correction's result (which learns them with F, and "
                "which tell then refits), or fix them: Campaign(system.at(theta), ...)"
            )
        if not isinstance(gp, CorrectionGP):
            raise InputError(f"gp: expected a CorrectionGP (the prior), got {type(gp).__name__}")
        if criterion not in CRITERIA:
            raise InputError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
        if proxy is not None and proxy not in PROXIES:
            raise InputError(f"proxy: expected one of {PROXIES} or None, got {proxy!r}")
        self.candidates = check_candidates(candidates, self.system, dtype=gp.dtype, device=gp.device)
        self.times = check_times(times, dtype=gp.dtype, device=gp.device)
        #: the candidates' input profiles (a system with inputs), or None
        self.controls = None
        if controls is not None:
            if getattr(controls, "_function", None) is not None:
                raise InputError(
                    "controls: expected the candidates' profiles as samples (a Campaign saves them), got a function "
                    "u(t): sample it, Controls(knots, controls.at(knots))"
                )
            self.controls = self.system.check_controls(controls, self.candidates.shape[0]).to(
                dtype=gp.dtype, device=gp.device
            )
        self.prior = gp  # fitted: its hyperparameters and its samples are where the campaign starts
        if domain is not None:
            domain = check_domain(domain, "domain (one (lo, hi) per correction input)", dim=self.system.input_dim)
        self.config = {
            "criterion": criterion,
            "proxy": proxy,
            "domain": None if domain is None else [list(map(float, b)) for b in domain],
            "domain_size": domain_size,
            "derivative": derivative,
            "noise_std": check_real(noise_std, "noise_std", minimum=0.0),
            "refit_after": 4 * self.times.numel()
            if refit_after is None
            else check_positive_int(refit_after, "refit_after", minimum=0),
            "pilot": check_positive_int(pilot, "pilot", minimum=0),
            "seed": check_positive_int(seed, "seed", minimum=0),
        }
        if self.config["pilot"] > self.candidates.shape[0]:
            raise InputError(f"pilot: expected at most the {self.candidates.shape[0]} candidates, got {pilot}")
        self.generator = torch.Generator().manual_seed(self.config["seed"])
        self.gp = self.prior
        self.history: list[dict] = []
        self.asked: list[int] = []  # every candidate index handed out, in order
        self.pending: list[int] = []  # asked, not yet told
        self.measured: list[int] = []  # candidate index per told experiment (-1: not a candidate)
        self._inputs: list[torch.Tensor] = []
        self._targets: list[torch.Tensor] = []
        self._noise: list[torch.Tensor | None] = []
        #: the measured trajectories and the Pipeline they were learned by (a campaign started from a fit; else None)
        self.data, self.pipeline = None, None
        if gp.is_fitted:  # what is known already: the first design is conditioned on the samples gp was fitted on
            self._hold(gp)
            data, pipeline = getattr(gp, "trajectories_", None), getattr(gp, "pipeline_", None)
            if isinstance(data, Trajectories) and isinstance(pipeline, Pipeline):  # fit_correction's: its data and rule
                self.data = data.to(dtype=gp.dtype, device=gp.device)
                self.pipeline = pipeline

    def _hold(self, gp: CorrectionGP) -> None:
        """Hold ``gp`` and the samples it was fitted on (each once)."""
        self._inputs = [gp.train_inputs_.detach().clone()]
        self._targets = [gp.train_targets_.detach().clone()]
        self._noise = [None if gp.train_noise_ is None else gp.train_noise_.detach().clone()]
        self.gp = gp

    # --------------------------------------------------------------------------------------------- state
    @property
    def num_samples(self) -> int:
        return sum(x.shape[0] for x in self._inputs)

    @property
    def designed_on(self) -> MisspecifiedSystem:
        """The system the next design runs on (:meth:`_designed_on` for the campaign's criterion)."""
        return self._designed_on(self._criterion())

    def _designed_on(self, criterion) -> MisspecifiedSystem:
        """The system the design ``criterion`` runs on. With uncertain parameters: for the readings' criterion the
        system itself (theta integrated out about the fit's posterior, :mod:`._readings_theta`); for the criteria of
        correction samples G at theta's posterior mean (a plug-in: theta's spread is not in their gains)."""
        if self.system.parameters is None or isinstance(criterion, ReadoutCriterion):
            return self.system
        return self.system.at(self.gp.parameters_.mean)

    @property
    def num_experiments(self) -> int:
        return len(self.measured) if self.data is None else self.data.num_experiments

    @property
    def remaining(self) -> torch.Tensor:
        """Indices of the candidates not asked for yet."""
        mask = torch.ones(self.candidates.shape[0], dtype=torch.bool)
        mask[self.asked] = False
        return torch.nonzero(mask).flatten()

    def __repr__(self) -> str:
        return (
            f"Campaign(system='{self.system.name}', candidates={self.candidates.shape[0]}, "
            f"experiments={self.num_experiments}, samples={self.num_samples}, pending={len(self.pending)}, "
            f"criterion='{self.config['criterion']}')"
        )

    # --------------------------------------------------------------------------------------------- ask
    def ask(self, k: int = 1):
        """The next ``k`` initial conditions ``(k, d)``, designed greedily given everything measured so far; for a
        campaign with ``controls``, ``(states (k, d), their profiles)``: run each experiment under its profile.

        While fewer than ``pilot`` experiments were asked for, the batch (or its first part) is drawn at random.
        The picks are recorded in ``history`` and stay pending until told.
        """
        remaining = self.remaining
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise InputError(f"k: expected a positive integer number of experiments, got {k!r}")
        if k > remaining.numel():
            raise InputError(f"k: expected at most the {remaining.numel()} candidates not asked for yet, got {k}")
        start = time.perf_counter()
        n_pilot = min(k, max(0, self.config["pilot"] - len(self.asked)))
        state = self.generator.get_state()
        try:
            picks, gains, info = self._design(k, n_pilot, remaining)
        except BaseException:
            self.generator.set_state(state)  # nothing changes when the design fails
            raise
        self.asked += picks
        self.pending += picks
        self.history.append(
            {
                "event": "ask",
                "round": sum(h["event"] == "ask" for h in self.history) + 1,
                "indices": picks,
                "points": self.candidates[picks].tolist(),
                "gains": gains,
                "pilot": n_pilot,
                "design": info,
                "seconds": time.perf_counter() - start,
            }
        )
        if self.controls is not None:
            return self.candidates[picks].clone(), self.controls[picks]
        return self.candidates[picks].clone()

    def _design(self, k: int, n_pilot: int, remaining: torch.Tensor) -> tuple[list[int], list, dict]:
        """The picks (pilot draws first, then the greedy design), their gains and the design's diagnostics."""
        picks: list[int] = []
        gains: list[float | None] = []
        if n_pilot:
            order = torch.randperm(remaining.numel(), generator=self.generator)[:n_pilot]
            picks = remaining[order].tolist()
            gains = [None] * n_pilot  # drawn, not designed
        info: dict = {}
        if k > n_pilot:
            mask = torch.ones(remaining.numel(), dtype=torch.bool)
            mask[[int((remaining == p).nonzero()[0, 0]) for p in picks]] = False
            pool = remaining[mask]
            proxy = self.config["proxy"] or ("corrected" if self.gp.is_fitted else "known")
            criterion = self._criterion()
            plan = greedy(
                self.candidates[pool],
                k - n_pilot,
                system=self._designed_on(criterion),
                times=self.times,
                gp=self.gp,
                criterion=criterion,
                proxy=Proxy(proxy),
                controls=None if self.controls is None else self.controls[pool.tolist()],
                executor=self.executor,
            )
            picks += pool[plan.indices.cpu()].tolist()
            gains += plan.gains.tolist()
            info = {key: v for key, v in plan.diagnostics.items() if isinstance(v, (int, float, str, bool))}
            info["selection_seconds"] = plan.elapsed
        return picks, gains, info

    def _criterion(self):
        """The configured criterion (the domain's with its box and quadrature), or the readings' one when the data
        carry a readout (:func:`campaign_criterion`). With the information criterion the domain only scores the
        error over D in :meth:`tell`."""
        cfg = self.config
        criterion = cfg["criterion"]
        if criterion == "domain":
            criterion = DomainCriterion(cfg["domain"], cfg["domain_size"])
        return campaign_criterion(criterion, self.data, self.gp, self.system)

    # --------------------------------------------------------------------------------------------- tell
    def _match(self, y0: torch.Tensor, pending: list[int], profile=None) -> int:
        """The first of ``pending`` (candidate indices) whose initial condition is ``y0`` (-1: none); with a campaign's
        ``controls``, only the pending asks whose profile is ``profile`` (equal at the observation times)."""
        if self.controls is not None:
            told = profile.at(self.times.unsqueeze(0)).to(self.candidates)
            pending = [
                p
                for p in pending
                if torch.allclose(self.controls[[p]].at(self.times.unsqueeze(0)), told, rtol=1e-9, atol=1e-12)
            ]
        if not pending:
            return -1
        pend = self.candidates[pending]
        scale = 1.0 + pend.abs().amax(-1)
        hit = ((pend - y0).abs().amax(-1) <= MATCH_TOL * scale).nonzero()
        if hit.numel():
            return pending[int(hit[0, 0])]
        # a lab measures the first state with noise: the nearest pending ask, in units of the candidates' range
        span = (self.candidates.amax(0) - self.candidates.amin(0)).clamp_min(torch.finfo(pend.dtype).tiny)
        dist = ((pend - y0).abs() / span).amax(-1)
        order = torch.argsort(dist)
        near = float(dist[order[0]]) <= NEAR_TOL
        unique = dist.numel() == 1 or float(dist[order[1]]) >= 2 * float(dist[order[0]])
        return pending[int(order[0])] if near and unique else -1

    def _given_asks(self, asked, n: int, pending: list[int]) -> list[int]:
        """The candidate indices ``asked`` names for ``n`` told experiments, checked against the pending asks."""
        if isinstance(asked, str) and asked == "pending":
            if n > len(pending):
                raise InputError(
                    f"asked='pending': expected at most the {len(pending)} pending asks, got {n} experiments; pass "
                    "asked=[index or -1 per experiment]"
                )
            return pending[:n]
        ok = isinstance(asked, (list, tuple)) and all(isinstance(i, int) and not isinstance(i, bool) for i in asked)
        if not ok or len(asked) != n:
            raise InputError(
                f"asked: expected 'pending' or a list of {n} candidate indices (-1: not asked for), got {asked!r:.100}"
            )
        wrong = [i for i in asked if i >= 0 and (i not in pending or asked.count(i) > 1)]
        if wrong:
            raise InputError(
                f"asked: expected pending asks (each once) or -1, got {wrong} (pending: {pending}); tell experiments "
                "nobody asked for as -1"
            )
        return list(asked)

    def tell(self, trajectories: Trajectories, *, asked=None) -> CorrectionGP:
        """Add measured experiments; returns the refitted GP (also ``self.gp``).

        ``asked``: the candidate index each experiment answers (``-1``: not asked for), or ``"pending"``: the
        experiments answer the pending asks in the order they were asked. By default each experiment's first state is
        matched to a pending ask: exactly, or, a measured and so noisy first state, the nearest pending ask within
        10 % of the candidates' range in every coordinate when it is at most half as far as any other pending ask.
        Experiments nobody asked for are accepted and noted as such in the history. An experiment the campaign holds
        already (the same times and values: the data of the fit it started from, or one told before) is recognised
        and not added again; with nothing new, the model is unchanged.

        How the model is refitted: a campaign started from :func:`~torchmisspec.fit_correction`'s result holds its
        trajectories and refits on them and the new ones with the same :class:`~torchmisspec.Pipeline`
        (``gp.pipeline_``: the same stages, candidates and choice rule: held-out experiments, do no harm);
        otherwise the samples of :func:`~torchmisspec.correction_samples` (the campaign's ``derivative`` and
        ``noise_std``) are added and the GP refitted by marginal likelihood (``refit_after``); the campaign's
        ``derivative`` and ``noise_std`` apply to this second way only (the first uses the fit's own options). Nothing
        changes if anything fails (bad input, a failed fit).
        """
        traj = self._checked(trajectories)
        start = time.perf_counter()
        known = known_experiments(traj, self.data)
        told = traj.num_experiments
        if all(known):
            return self._noted(told, start)
        if any(known):
            traj = traj[[k for k, seen in enumerate(known) if not seen]]
            if isinstance(asked, (list, tuple)) and len(asked) == told:  # another length: _given_asks says so
                asked = [a for a, seen in zip(asked, known, strict=True) if not seen]
        matched, pending = self._matched(traj, asked)
        state = self.generator.get_state()
        try:
            if self.data is not None:
                data = Trajectories.concatenate([self.data, traj])
                gp, note = self.pipeline.fit(data, self.system, progress=False), "refitted by fit_correction"
            else:
                data, (gp, note) = None, self._refit_samples(traj)
        except BaseException:
            self.generator.set_state(state)  # a retry draws what an uninterrupted campaign draws
            raise
        # every check passed and the fit worked: commit
        if data is not None:
            self.data = data
            self._hold(gp)
        self.pending = pending
        self.measured += matched
        self.gp = gp
        self._record_tell(matched, note, start, told - len(matched))
        return gp

    def _checked(self, trajectories) -> Trajectories:
        if not isinstance(trajectories, Trajectories):
            raise InputError(f"trajectories: expected a Trajectories, got {type(trajectories).__name__}")
        if trajectories.state_dim != self.system.state_dim:
            raise ShapeError(
                f"trajectories: expected states of dimension {self.system.state_dim} (system "
                f"'{self.system.name}'), got {trajectories.state_dim}"
            )
        if self.controls is not None and trajectories.controls is None:
            raise InputError(
                "trajectories: expected the input profiles the experiments ran under (this campaign's experiments "
                "have them), got trajectories without controls: tell the measured trajectories with the profiles "
                "they ran under (Trajectories(..., controls=...))"
            )
        return trajectories.to(dtype=self.candidates.dtype, device=self.candidates.device)

    def _matched(self, traj: Trajectories, asked) -> tuple[list[int], list[int]]:
        """The candidate each experiment answers (-1: none) and the asks still pending after them."""
        matched, pending = [], list(self.pending)
        y0 = traj.initial_conditions
        if asked is None:
            for k, row in enumerate(y0):
                idx = self._match(row, pending, None if self.controls is None else traj.controls[[k]])
                if idx >= 0:
                    pending.remove(idx)  # duplicates of a candidate match one pending ask each
                matched.append(idx)
        else:
            matched = self._given_asks(asked, y0.shape[0], pending)
            pending = [p for p in pending if p not in matched]
        return matched, pending

    def _refit_samples(self, traj: Trajectories) -> tuple[CorrectionGP, str]:
        samples = correction_samples(
            traj,
            self.system,
            derivative=self.config["derivative"],
            noise_std=self.config["noise_std"],
            generator=self.generator,
        )
        inputs = self._inputs + [samples.inputs]
        targets = self._targets + [samples.targets]
        noise = self._noise + [samples.noise]
        gp, note = self._fit(inputs, targets, noise)
        self._inputs, self._targets, self._noise = inputs, targets, noise  # the caller commits the rest
        return gp, note

    def _noted(self, known: int, start: float) -> CorrectionGP:
        """A tell of experiments the campaign holds already: recorded, nothing added, the model unchanged."""
        self._record_tell([], "nothing new: every experiment told is held already; model unchanged", start, known)
        return self.gp

    def _record_tell(self, matched: list[int], note: str, start: float, known: int) -> None:
        gp = self.gp
        entry = {
            "event": "tell",
            "experiments": len(matched),
            "indices": matched,
            "unrequested": sum(i < 0 for i in matched),
            "already_held": known,
            "samples": self.num_samples,
            "hyperparameters": plain.hyperparameters(gp),
            "learned": note in ("learned", "refitted by fit_correction"),
            "note": note,
            "seconds": time.perf_counter() - start,
        }
        if entry["unrequested"]:
            entry["note"] += f"; {entry['unrequested']} experiment(s) not asked for (initial conditions not pending)"
        if known and matched:
            entry["note"] += f"; {known} experiment(s) held already (the same times and values), not added again"
        if self.system.has_correction and (self.config["domain"] is not None or self.system.domain is not None):
            entry["error"] = correction_error(gp, self.system, domain=self.config["domain"], resolution=51)
        self.history.append(entry)

    def _fit(self, inputs, targets, noise) -> tuple[CorrectionGP, str]:
        X, Y = torch.cat(inputs), torch.cat(targets)
        known = None
        if any(n is not None for n in noise):
            known = torch.cat([torch.zeros_like(t) if n is None else n for n, t in zip(noise, targets, strict=True)])
        refit = self.config["refit_after"]
        if refit and X.shape[0] >= refit:
            # the prior's kernel and settings, every hyperparameter learned
            p = self.prior
            learner = p.clone(kernel=p.kernel_spec, lengthscale=None, outputscale=None, noise_variance=None)
            try:
                return learner.fit(X, Y, noise=known), "learned"
            except TorchMisspecError as exc:
                note = f"hyperparameters not learned ({type(exc).__name__}: {exc}); kept the prior's"
        else:
            note = "prior hyperparameters (fewer samples than refit_after)" if refit else "prior hyperparameters"
        # the starting model's hyperparameters (fitted, per-output ones included, or given), conditioned
        return self.prior.condition(X, Y, noise=known), note

    # --------------------------------------------------------------------------------------------- files
    def save(self, path: str | Path) -> Path:
        """Write the campaign (configuration, candidates, data, pending asks, history, model, random state) to
        ``path``, atomically. The system is not saved (it is code): pass it again to :meth:`load`."""
        path = check_writable(path)
        blob = {
            "format": FORMAT,
            "version": VERSION,
            "system": {"name": self.system.name, "state_dim": self.system.state_dim},
            "config": dict(self.config),
            "candidates": self.candidates.cpu(),
            "times": self.times.cpu(),
            "controls": None if self.controls is None else plain.controls_blob(self.controls),
            "prior": _persistence.config_of(self.prior),
            "prior_model": _persistence.to_blob(self.prior) if self.prior.is_fitted else None,
            "model": _persistence.to_blob(self.gp) if self.gp.is_fitted else None,
            "inputs": [x.cpu() for x in self._inputs],
            "targets": [y.cpu() for y in self._targets],
            "noise": [None if n is None else n.cpu() for n in self._noise],
            "asked": list(self.asked),
            "pending": list(self.pending),
            "measured": list(self.measured),
            "history": self.history,
            "generator": self.generator.get_state(),
            "data": None if self.data is None else plain.data_blob(self.data),
            "fit_options": None if self.pipeline is None else plain.options_blob(self.pipeline.keywords()),
        }
        tmp = path.with_name(path.name + ".tmp")
        with writing(path):
            torch.save(blob, tmp)
            os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | Path, system: MisspecifiedSystem) -> Campaign:
        """Resume a campaign written by :meth:`save`; ``system`` must be the one it was run with (checked by name
        and dimension). A file that is not a campaign, or is damaged, raises an InputError naming what is wrong."""
        path = Path(check_path(path))
        blob = _persistence.read_safely(path, "Campaign", "Campaign.save")
        if not isinstance(system, MisspecifiedSystem):
            raise InputError(f"system: expected a MisspecifiedSystem, got {type(system).__name__}")

        def field(key, kind):
            return _persistence._field(blob, key, kind, path, "Campaign")

        plain.check_header(blob, path, system, field, FORMAT, VERSION)
        prior = _persistence.from_config(CorrectionGP, field("prior", dict), f"{path} (field 'prior')")
        if blob.get("prior_model") is not None:  # a campaign started from a fitted GP
            prior = _persistence.from_blob(CorrectionGP, blob["prior_model"], f"{path} (field 'prior_model')")
        cfg = field("config", dict)
        try:
            camp = cls(
                system,
                field("candidates", torch.Tensor),
                field("times", torch.Tensor),
                prior,
                **{k: cfg[k] for k in ("criterion", "proxy", "domain", "domain_size", "derivative")},
                noise_std=cfg["noise_std"],
                refit_after=cfg["refit_after"],
                pilot=cfg["pilot"],
                seed=cfg["seed"],
                controls=plain.controls_from(blob.get("controls"), path),
            )
        except (KeyError, TypeError) as exc:
            raise InputError(f"{path}: field 'config' is damaged ({type(exc).__name__}: {exc})") from exc
        n, d_in = camp.candidates.shape[0], system.input_dim
        inputs, targets, noise = plain.checked_samples(field, path, d_in, system.output_dim)
        lists, history = plain.checked_records(field, path, n)
        dd = {"dtype": camp.candidates.dtype, "device": camp.candidates.device}
        camp._inputs = [x.to(**dd) for x in inputs]
        camp._targets = [y.to(**dd) for y in targets]
        camp._noise = [None if e is None else e.to(**dd) for e in noise]
        camp.asked, camp.pending, camp.measured = lists["asked"], lists["pending"], lists["measured"]
        camp.history = history
        state = field("generator", torch.Tensor)
        try:
            camp.generator.set_state(state)
        except RuntimeError as exc:
            raise InputError(f"{path}: field 'generator' is damaged ({exc})") from exc
        camp.data = plain.data_from(blob.get("data"), path, **dd)
        camp.pipeline = plain.pipeline_from(blob.get("fit_options"), path)
        if (camp.data is None) != (camp.pipeline is None):
            raise InputError(f"{path}: expected both 'data' and 'fit_options' or neither; the file is damaged")
        model = blob.get("model")
        if model is not None:
            camp.gp = _persistence.from_blob(CorrectionGP, model, path)
        elif camp._inputs:
            raise InputError(f"{path}: the campaign holds samples but no fitted model; the file is damaged")
        return camp
