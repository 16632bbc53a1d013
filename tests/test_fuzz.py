"""Property-based fuzz of the public API: each case changes ONE argument of a valid call to a bad value.

The promise checked: the call either returns a result without NaN/inf, or raises a ``TorchMisspecError`` whose
message says what was expected and what it got (no raw ``TypeError`` from inside torch for a value of the wrong
type), within a time bound. The default run draws a few hundred cases; ``-m slow`` runs a longer profile.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchmisspec as tms
from torchmisspec import plotting
from torchmisspec.prediction._bands import TrajectoryPosterior

DT = torch.float64
SYSTEM = tms.systems.paper_linear()
TIMES = torch.linspace(0.0, 6.0, 6, dtype=DT)
Y0 = torch.tensor([[0.5, -0.3], [0.2, 0.7], [-0.6, 0.1]], dtype=DT)
TRAJ = tms.simulate(SYSTEM, Y0, TIMES)
SAMPLES = tms.correction_samples(TRAJ, SYSTEM, derivative="oracle", noise_std=1e-3, generator=torch.Generator())
PRIOR = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4)
FITTED = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4).fit(SAMPLES.inputs, SAMPLES.targets)
CANDIDATES = tms.design.candidates.grid(SYSTEM.domain, 4)
MODEL = tms.CorrectedODE(SYSTEM, FITTED)
READOUT = tms.Readout([[1.0, 1.0]], ["total"])
READINGS = READOUT(TRAJ.states)
LEVELS = torch.linspace(0.0, 1.0, 12, dtype=DT).reshape(2, 6, 1)
FILES = Path(tempfile.mkdtemp(prefix="torchmisspec-fuzz-"))
PRIORS = {"k": (1.0, 0.1)}
CURVE = np.array([0.3, 0.2, 0.1])
TIME_BOUND = 20.0  # seconds per call, on a loaded 2-core machine
#: examples of the long profile (slow tests); TORCHMISSPEC_FUZZ_EXAMPLES=20000 for the run before a release
LONG_EXAMPLES = int(os.environ.get("TORCHMISSPEC_FUZZ_EXAMPLES", "1500"))

# ---------------------------------------------------------------------------------------------- bad values
_nan = Y0.clone()
_nan[1, 0] = float("nan")
_inf = Y0.clone()
_inf[0, 1] = float("inf")
BAD_ARRAYS = [
    _nan,
    _inf,
    torch.zeros(0, 2, dtype=DT),
    torch.zeros(3, dtype=DT),
    torch.zeros(3, 3, dtype=DT),
    torch.zeros(2, 2, 2, dtype=DT),
    Y0.to(torch.complex128),
    Y0 > 0,
    Y0.half(),
    "abc",
    None,
    object(),
    1e300 * Y0,
    -1e300 * Y0,
    1e-300 * Y0,
    np.array([[1 + 2j, 0], [0, 1]]),
    [[0.1, 0.2], [0.3]],
    float("nan"),
    tms.signals.Controls(TIMES, LEVELS),  # objects with __len__ / __getitem__: an index made of one crashed torch
    TRAJ,
]
#: for elementwise maps (G, F, the selection of F's inputs, the posterior's sd ratio): a NaN state gives a NaN value
#: there, as a missing entry stays missing; every other bad array is refused
BAD_FINITE_ARRAYS = BAD_ARRAYS[2:]
BAD_TIMES = [
    torch.tensor([0.0, 1e300], dtype=DT),
    torch.tensor([0.0, 0.0, 1.0], dtype=DT),
    torch.tensor([1.0, 0.0], dtype=DT),
    torch.zeros(0, dtype=DT),
    torch.tensor([0.0, float("nan")], dtype=DT),
    torch.tensor([0.0, 1e-300, 2e-300], dtype=DT),
    torch.zeros(2, 2, 2, dtype=DT),
    "0:6:11",
    None,
    torch.tensor([0.0, 1.0 + 1j]),
]
BAD_NUMBERS = [0, -1, 2.5, float("nan"), float("inf"), -float("inf"), 10**400, 1e-320, True, "3", None, [1], 1e300]


def _no_nan(out) -> None:
    """Every tensor reachable from a result is finite (NaN allowed only where documented: unset gains)."""
    if isinstance(out, torch.Tensor):
        if out.is_floating_point():
            assert bool(torch.isfinite(out).all()), "non-finite values returned"
    elif isinstance(out, float):
        assert math.isfinite(out), "non-finite float returned"
    elif isinstance(out, (tuple, list)):
        for item in out:
            _no_nan(item)
    elif isinstance(out, TrajectoryPosterior):  # a draw that left the region is NaN from there on (documented)
        gone = torch.isnan(out.samples).any(-1)  # (S, B, T)
        assert bool((gone.cummax(-1).values == gone).all()), "a draw is NaN before it left the region"
        assert not bool(torch.isinf(out.samples).any()), "infinite draws returned"
        assert bool((out.fraction_remaining == 1 - gone[..., -1].double().mean(0)).all())
        for name in ("times", "mean_path", "support"):
            _no_nan(getattr(out, name))
    elif hasattr(out, "__dataclass_fields__") and not isinstance(out, tms.design.DesignResult):
        for name in out.__dataclass_fields__:
            _no_nan(getattr(out, name))
    elif isinstance(out, tms.design.DesignResult):
        _no_nan(out.indices.double())
        _no_nan(out.points)
    elif isinstance(out, np.ndarray):
        assert bool(np.isfinite(out).all()), "non-finite values returned"
    else:  # a wrapper returning something unexpected (a bound method, ...) would check nothing
        assert out is None or isinstance(out, (int, str)), f"unexpected result type {type(out).__name__}"


def _scaled_rms(d: np.ndarray) -> float:
    """The root mean square of ``d`` without overflow (numpy, scaled by the largest magnitude)."""
    scale = float(np.abs(d).max()) or 1.0
    return scale * float(np.sqrt(np.mean((d / scale) ** 2)))


def _rmse_oracle(predicted=None, true=None):
    a = np.asarray(TRAJ.states if predicted is None else predicted, dtype=np.float64)
    b = np.asarray(TRAJ.states if true is None else true, dtype=np.float64)
    return _scaled_rms(a - b)


def _mean_se_oracle(values=(1.0, 2.0, 3.0)):
    v = np.asarray(values, dtype=np.float64)
    scale = float(np.abs(v).max(axis=0).max()) or 1.0
    w = v / scale
    se = 0.0 if len(w) == 1 else np.std(w, axis=0, ddof=1) * scale / math.sqrt(len(w))
    return np.mean(w, axis=0) * scale, se


def _information_oracle(points=None):
    """0.5 d_out logdet(I + K / noise) with the prior's RBF kernel written out (lengthscale 1, output scale 4e-5,
    noise 1e-4)."""
    x = np.asarray(Y0 if points is None else points, dtype=np.float64)
    sq = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    K = 4e-5 * np.exp(-sq / 2.0)
    return 0.5 * 2 * np.linalg.slogdet(np.eye(len(x)) + K / 1e-4)[1]


def _rbf(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The fitted GP's kernel written out: RBF, lengthscale 1, output scale 4e-5."""
    return 4e-5 * np.exp(-((a[:, None, :] - b[None, :, :]) ** 2).sum(-1) / 2.0)


def _posterior_oracle(x=Y0):
    """The GP posterior by a hand-written Cholesky solve (numpy): mean k*(K + s2 I)^-1 y and variance k** - ..."""
    x = np.asarray(x, dtype=np.float64)
    inputs, targets = SAMPLES.inputs.numpy(), SAMPLES.targets.numpy()
    chol = np.linalg.cholesky(_rbf(inputs, inputs) + 1e-4 * np.eye(len(inputs)))
    cross = _rbf(x, inputs)
    v = np.linalg.solve(chol, cross.T)
    mean = cross @ np.linalg.solve(chol.T, np.linalg.solve(chol, targets))
    variance = np.maximum(4e-5 - (v**2).sum(0), 0.0)
    return mean, np.repeat(variance[:, None], targets.shape[1], axis=1)


def _fd_oracle(states=TRAJ.states, times=TIMES, order=2):
    assert order == 2, "only order 2 has a numpy reference"
    return np.gradient(np.asarray(states, dtype=np.float64), np.asarray(times, dtype=np.float64), axis=-2, edge_order=2)


def _readout_oracle(matrix=((1.0, 1.0),), names=("total",)):
    return np.asarray(Y0) @ np.asarray(matrix, dtype=np.float64).T


def _parse_oracle(text="total = a + 2*b"):
    known = {"total = a + 2*b": [[1.0, 2.0]]}
    assert text in known, f"accepted {text!r}, which is not a readout of a and b"
    return np.asarray(known[text])


def _grid_oracle(domain=((-1.0, 1.0), (-1.0, 1.0)), size=3):
    axes = [np.linspace(lo, hi, size) for lo, hi in np.asarray(domain, dtype=np.float64)]
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=-1)


def _box_grid_oracle(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=5):
    """The grid and the trapezoid rule's weights: a product over the axes of h/2, h, ..., h, h/2."""
    bounds = np.asarray(domain, dtype=np.float64)
    weights = np.ones([resolution] * len(bounds))
    for j, (lo, hi) in enumerate(bounds):
        w = np.full(resolution, (hi - lo) / (resolution - 1))
        w[[0, -1]] /= 2
        shape = [1] * len(bounds)
        shape[j] = resolution
        weights = weights * w.reshape(shape)
    return _grid_oracle(domain, resolution), weights.ravel()


def _controls_oracle(knots=TIMES, values=LEVELS, kind="previous"):
    """Piecewise-constant or linear profiles evaluated with numpy (searchsorted / interp)."""
    knots, values, t = np.asarray(knots, dtype=np.float64), np.asarray(values, dtype=np.float64), TIMES.numpy()
    out = np.empty((values.shape[0], len(t), values.shape[-1]))
    for k in range(values.shape[0]):
        for j in range(values.shape[-1]):
            if kind == "previous":
                out[k, :, j] = values[k, np.clip(np.searchsorted(knots, t, side="right") - 1, 0, None), j]
            else:
                out[k, :, j] = np.interp(t, knots, values[k, :, j])
    return out


def _simulate_oracle(y0=Y0, times=TIMES, max_steps=2000):
    """The true system solved by scipy (DOP853, tolerances 1e-12)."""
    from scipy.integrate import solve_ivp

    def rhs(_, y):
        return SYSTEM.true_rhs(torch.as_tensor(y, dtype=DT).reshape(-1, 2)).reshape(-1).numpy()

    y0, t = np.asarray(y0, dtype=np.float64), np.asarray(times, dtype=np.float64)
    sol = solve_ivp(rhs, (t[0], t[-1]), y0.reshape(-1), method="DOP853", t_eval=t, rtol=1e-12, atol=1e-14)
    return sol.y.T.reshape(len(t), *y0.shape).transpose(1, 0, 2)


def _agrees(out, expected, rtol: float = 1e-9) -> None:
    """A result equals an independent computation (numpy, scipy), to ``rtol`` or the rounding of the result's dtype."""
    for got, want in zip(
        out if isinstance(out, tuple) else (out,), expected if isinstance(expected, tuple) else (expected,), strict=True
    ):
        if isinstance(got, torch.Tensor):
            rtol = max(rtol, 100 * torch.finfo(got.dtype).eps)
            got = got.detach().cpu().double()
        got = np.asarray(got, dtype=np.float64)
        assert np.allclose(got, want, rtol=rtol, atol=1e-300), (got, want)


def _check(call, **kwargs) -> None:
    """The call returns a finite result (equal to an independent computation where the call has one, its
    ``oracle``), or raises a package error whose message names what was expected and what was received
    ("expected ..., got ..."), within the time bound."""
    start = time.perf_counter()
    try:
        out = call(**kwargs)
    except (tms.InputError, tms.ShapeError, tms.BudgetError) as exc:  # bad input: say what was expected and got
        message = str(exc)
        assert "expected" in message and ("got" in message or "received" in message), message
    except tms.TorchMisspecError:  # a failure of the work itself (a blow-up, a failed fit) names what happened
        pass
    else:
        _no_nan(out)
        oracle, rtol = ORACLES.get(call, (None, None))
        if oracle is not None:
            _agrees(out, oracle(**kwargs), rtol)
    assert time.perf_counter() - start < TIME_BOUND


# ---------------------------------------------------------------------------------------------- the calls
def _simulate(y0=Y0, times=TIMES, max_steps=2000):
    return tms.simulate(SYSTEM, y0, times, max_steps=max_steps).states


def _samples(states=TRAJ.states, times=TIMES, derivative="central", noise_std=0.0, order=2, window=5, degree=2):
    traj = tms.Trajectories(times, states)
    return tms.correction_samples(
        traj, SYSTEM, derivative=derivative, noise_std=noise_std, order=order, window=window, degree=degree
    )


def _gp(lengthscale=None, outputscale=None, noise_variance=None, max_iter=50, degree=2, kernel="rbf"):
    return (
        tms.CorrectionGP(
            kernel=kernel,
            lengthscale=lengthscale,
            outputscale=outputscale,
            noise_variance=noise_variance,
            max_iter=max_iter,
            degree=degree,
        )
        .fit(SAMPLES.inputs, SAMPLES.targets)
        .predict(Y0)
    )


def _fit(inputs=SAMPLES.inputs, targets=SAMPLES.targets):
    return tms.CorrectionGP(max_iter=30).fit(inputs, targets).predict_mean(Y0)


def _predict(x=Y0):
    posterior = FITTED.predict(x)
    return posterior.mean, posterior.variance


def _predict_mean(x=Y0):
    return FITTED.predict_mean(x)


def _ode(y0=Y0[:2], times=TIMES, max_steps=2000):
    return tms.CorrectedODE(SYSTEM, FITTED).predict(y0, times, solver=tms.Solver(max_steps=max_steps))


def _greedy(candidates=CANDIDATES, budget=3, times=TIMES, method="lazy"):
    return tms.design.greedy(candidates, budget, system=SYSTEM, times=times, gp=PRIOR, method=method)


def _random(candidates=CANDIDATES, budget=3):
    return tms.design.random(candidates, budget, generator=torch.Generator().manual_seed(0))


def _information(points=Y0):
    return tms.design.information_gain(points, PRIOR, d_out=2)


def _rmse(predicted=TRAJ.states, true=TRAJ.states):
    return tms.trajectory_rmse(predicted, true)


def _fd(states=TRAJ.states, times=TIMES, order=2):
    return tms.finite_difference(states, times, order=order)


def _grid(domain=((-1.0, 1.0), (-1.0, 1.0)), size=3):
    return tms.design.candidates.grid(domain, size)


BAD_INDICES = [[0.7], [True, False], [-1], [100], [], "ab", None, [[0, 1]], torch.tensor([0.5, 1.0]), 1.5, [10**30]]
#: selections of experiments (Trajectories / Controls / CorrectionSamples indexing)
BAD_SELECTIONS = BAD_INDICES + [
    3, -4, slice(None, None, -1), slice(0, 0), {0: 1}, ..., True, (torch.tensor([[0.1, 0.2]]), LEVELS), TRAJ,
    torch.tensor([True, False]), np.array([0.5]),
]  # fmt: skip
BAD_DEVICES = ["bogus", 3, torch.int64, torch.complex128, torch.bool, "meta", "cuda:99", None, torch.float16]
BAD_DIMS = [(0, 5), (0,), "ab", None, (0.5, 1), (True, False), (-3, 0)]
BAD_OUTPUTS = ["/proc/x.png", str(FILES), 3, str(FILES / "figure.pdf"), str(FILES / "no" / "such" / "f.png")]
BAD_NAMES = ["", ["x"], [1, 2], ["a", "a"], 3, [None, "b"], ["a", " "]]
BAD_PARTITIONS = [["a", "b"] * 8, [True, False] * 8, [0.5] * 16, [0] * 3, None, [float("nan")] * 16]
BAD_CAPACITIES = [[10**30, 1], [-1, 2], [1.5, 2], {True: 2}, "ab", None, [float("inf"), 1], {"a": 1}]


def _trajectories(times=TIMES, states=TRAJ.states, state_names=("a", "b"), readings=READINGS):
    data = tms.Trajectories(times, states, state_names=state_names, readout=READOUT, readings=readings)
    return data.observed_values()[0].nan_to_num(0.0)


def _readout(matrix=((1.0, 1.0),), names=("total",)):
    return tms.Readout(matrix, names)(Y0)


def _parse(text="total = a + 2*b"):
    return tms.Readout.parse([text], ["a", "b"]).matrix


def _controls(knots=TIMES, values=LEVELS, kind="previous"):
    return tms.Controls(knots, values, kind=kind).at(TIMES.expand(2, -1))


def _system(state_dim=2, correction_inputs=(0,), correction_outputs=(1,), domain=((-1, 1),)):
    system = tms.MisspecifiedSystem(
        lambda y: -y,
        state_dim,
        correction_inputs=correction_inputs,
        correction_outputs=correction_outputs,
        domain=domain,
    )
    return system.known_rhs(Y0)


def _smooth(states=TRAJ.states, times=TIMES, window=5, degree=2):
    return tms.smoothed_derivative(states, times, window=window, degree=degree)


def _correction_error(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=11, metric="integrated"):
    return tms.correction_error(FITTED, SYSTEM, domain=domain, resolution=resolution, metric=metric)


def _marginal_gains(indices=(0, 2), candidates=CANDIDATES):
    return tms.design.marginal_gains(indices, candidates, system=SYSTEM, times=TIMES, gp=PRIOR)


def _partitioned(partition=[0, 1] * 8, capacities=(2, 2), budget=3):
    return tms.design.greedy(
        CANDIDATES,
        budget,
        system=SYSTEM,
        times=TIMES,
        gp=PRIOR,
        partition=tms.design.Partition(partition, capacities),
    )


def _sampling_times(initial_states=Y0[:2], times=TIMES, per_experiment=3):
    return tms.design.sampling_times(initial_states, times, per_experiment, system=SYSTEM, gp=PRIOR).times


def _posterior(y0=Y0[:2], times=TIMES, num_samples=4, scale=1.0):
    return MODEL.posterior(y0, times, num_samples=num_samples, scale=scale, generator=torch.Generator())


def _mean_se(values=(1.0, 2.0, 3.0)):
    return tms.metrics.mean_and_standard_error(values)


def _proxies(candidates=CANDIDATES[:4], times=TIMES, max_steps=2000):
    return tms.design.proxy_trajectories(SYSTEM, candidates, times, max_steps=max_steps)


def _variance_reduction(points=Y0, domain_size=64):
    return tms.design.variance_reduction(points, PRIOR, system=SYSTEM, domain_size=domain_size)


def _agnostic(candidates=CANDIDATES, budget=3, times=TIMES):
    return tms.design.agnostic(candidates, budget, system=SYSTEM, times=times, gp=PRIOR)


def _uniform_box(n=5, domain=((-1.0, 1.0), (-1.0, 1.0))):
    return tms.design.candidates.uniform_box(n, domain, generator=torch.Generator().manual_seed(0))


def _box_grid(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=5):
    return tms.design.candidates.box_grid(domain, resolution)


def _integrated_error(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=11):
    return tms.integrated_error(FITTED.predict_mean, SYSTEM.true_correction, domain, resolution=resolution)


def _campaign_ask(k=1, candidates=CANDIDATES, times=TIMES):
    return tms.design.Campaign(SYSTEM, candidates, times, PRIOR).ask(k)


def _campaign_tell(trajectories=TRAJ, asked=None):
    """One ask, the experiments told back, saved and loaded: the loaded campaign asks what the original asks."""
    campaign = tms.design.Campaign(SYSTEM, CANDIDATES, TIMES, PRIOR, derivative="oracle", noise_std=1e-3)
    campaign.ask(3)
    campaign.tell(trajectories, asked=asked)
    path = campaign.save(FILES / "campaign.json")
    again = tms.design.Campaign.load(path, SYSTEM)
    picks = campaign.ask(2)
    assert torch.equal(again.ask(2), picks), "a loaded campaign asks otherwise than the saved one"
    return picks


def _campaign_load(path=None, system=SYSTEM):
    campaign = tms.design.Campaign(SYSTEM, CANDIDATES, TIMES, PRIOR)
    campaign.ask(1)
    good = campaign.save(FILES / "good-campaign.json")
    return tms.design.Campaign.load(good if path is None else path, system).ask(1)


def _integrated_norm(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=11):
    return tms.integrated_norm(FITTED.predict_mean, domain, resolution=resolution)


def _integrate_over_box(domain=((-1.0, 2.0), (0.0, 1.0)), resolution=5, chunk=7):
    return tms.metrics.integrate_over_box(lambda x: x.sum(-1), domain, resolution=resolution, chunk=chunk)


def _integrate_oracle(domain=((-1.0, 2.0), (0.0, 1.0)), resolution=5, chunk=7):
    """The integral of x1 + x2 over the box (exact: the trapezoid rule integrates linear functions exactly)."""
    b = np.asarray(domain, dtype=np.float64)
    volume = float(np.prod(b[:, 1] - b[:, 0]))
    return volume * float((b[:, 0] + b[:, 1]).sum() / 2)


def _mse(domain=((-1.0, 1.0), (-1.0, 1.0)), resolution=11):
    return tms.metrics.mean_squared_error(FITTED.predict_mean, SYSTEM.true_correction, domain, resolution=resolution)


def _orbits(n=5, mass=0.2, half_width=2.0, min_radius=0.75):
    return tms.design.candidates.orbits(
        n, mass=mass, half_width=half_width, min_radius=min_radius, generator=torch.Generator().manual_seed(0)
    )


def _true_gain(indices=(0, 3), candidates=CANDIDATES, times=TIMES):
    return tms.design.true_information_gain(indices, candidates, system=SYSTEM, times=times, gp=PRIOR)


def _proxy_gap(indices=(0, 3), candidates=CANDIDATES, times=TIMES):
    bound = tms.design.proxy_gap_bound(indices, candidates, system=SYSTEM, times=times, gp=PRIOR)
    return 0.0 if bound == math.inf else bound  # inf is documented: Theorem 1 gives no bound there


def _proxy_check(indices=(0, 3), candidates=CANDIDATES, proxy="known"):
    check = tms.design.proxy_check(indices, candidates, system=SYSTEM, times=TIMES, gp=PRIOR, proxy=proxy)
    return check.proxy_gain, check.exact_gain, check.delta


def _refine(initial_states=Y0[:2], box=((-1.0, 1.0), (-1.0, 1.0)), steps=3, lr=0.1):
    return tms.design.refine(initial_states, system=SYSTEM, times=TIMES, gp=PRIOR, box=box, steps=steps, lr=lr).points


def _get_system(name="paper_linear"):
    return tms.systems.get_system(name).known_rhs(Y0)


def _load_system(spec="paper_linear"):
    return tms.systems.load_system(spec).known_rhs(Y0)


def _data_driven(system=SYSTEM):
    return tms.systems.data_driven(system).known_rhs(Y0)


POSTERIOR = MODEL.posterior(Y0[:2], TIMES, num_samples=8, scale=1.0, generator=torch.Generator().manual_seed(0))


def _interval(level=0.9):
    return POSTERIOR.interval(level)


def _read(readout=READOUT):
    return POSTERIOR.read(readout).interval(0.9)


def _plotted(draw):
    """A plotting call on a headless backend; the figure is closed whatever happens."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        draw()
    finally:
        plt.close("all")


def _plot_trajectories(states=TRAJ.states, dims=(0, 1), path=None):
    _plotted(lambda: plotting.plot_trajectories(states, dims=dims, path=path))


def _plot_design(candidates=CANDIDATES, picks=(0, 1), path=None):
    _plotted(lambda: plotting.plot_design(candidates, {"picks": picks}, path=path))


def _plot_bands(true_states=TRAJ.states[:2], index=0, levels=(0.9, 0.5)):
    _plotted(lambda: plotting.plot_prediction_bands(POSTERIOR, true_states=true_states, index=index, levels=levels))


def _plot_curves(ks=(1, 2, 3), curve=CURVE):
    _plotted(lambda: plotting.plot_error_curves(ks, {"a": curve}))


def _plot_calibration(nominal=(0.5, 0.9), empirical=CURVE[:2]):
    _plotted(lambda: plotting.plot_calibration(nominal, {"a": empirical}))


def _plot_error_map(domain=((-1.0, 1.0), (-1.0, 1.0)), traces=TRAJ.states, resolution=5):
    _plotted(lambda: plotting.plot_error_map(lambda y: y.norm(dim=-1), domain, traces=traces, resolution=resolution))


def _check_priors(parameters=PRIORS):
    priors = tms.parameters.check_priors(parameters)
    return priors.mean, priors.scale


(FILES / "empty.csv").write_text("")
(FILES / "header.csv").write_text("experiment,time,y0,y1\n")
(FILES / "binary.csv").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe" * 8)
(FILES / "ragged.csv").write_text("experiment,time,y0,y1\n0,0,1,2\n0,1,3\n")
(FILES / "words.csv").write_text("experiment,time,y0,y1\n0,0,a,2\n0,1,3,4\n")
(FILES / "repeat.csv").write_text("experiment,time,y0,y1\n0,0,1,2\n0,0,3,4\n")
(FILES / "inf.csv").write_text("experiment,time,y0,y1\n0,0,inf,2\n0,1,3,4\n")
(FILES / "text.npz").write_text("not an archive")
np.savez(FILES / "bare.npz", np.zeros(3))
np.savez(FILES / "objects.npz", times=np.array([0.0, 1.0]), states=np.array([[None, 1]], dtype=object))
(FILES / "text.pt").write_text("not a model")
(FILES / "empty.pt").write_bytes(b"")
BAD_FILES = [str(FILES / name) for name in sorted(p.name for p in FILES.iterdir())] + [
    str(FILES / "missing.csv"),
    str(FILES),
    "data.xlsx",
    3,
    None,
]


def _load_trajectories(path=None):
    TRAJ.save(FILES / "good.csv")
    return tms.Trajectories.load(FILES / "good.csv" if path is None else path).flat_states()


def _load_model(path=None):
    FITTED.save(FILES / "good.pt")
    return tms.CorrectionGP.load(FILES / "good.pt" if path is None else path).predict_mean(Y0)


# ---------------------------------------------------------------------------------------------- the 0.2 surface
CHEMO = tms.MisspecifiedSystem(
    lambda t, y, u: -u * y, 2, num_controls=1, state_names=["X", "S"], control_names=["D"],
    correction=lambda x: -0.1 * x[..., :1], correction_inputs=["X", "D"], correction_outputs=["X"], name="chemo",
)  # fmt: skip
CONTROLS = tms.signals.Controls(TIMES[[0, 3]], torch.tensor([[0.1, 0.3], [0.2, 0.1], [0.3, 0.2]], dtype=DT))
CTRAJ = tms.simulate(CHEMO, Y0 + 1.0, TIMES, controls=CONTROLS)
CSAMPLES = tms.correction_samples(CTRAJ, CHEMO, derivative="oracle")
CGP = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-2, noise_variance=1e-6).fit(CSAMPLES.inputs, CSAMPLES.targets)
CMODEL = tms.CorrectedODE(CHEMO, CGP)
U = torch.full((3, 1), 0.2, dtype=DT)


def _select(index=(0, 2), what="trajectories"):
    whole = {"trajectories": CTRAJ, "controls": CONTROLS}[what]
    picked = whole[index]
    return picked.flat_states() if what == "trajectories" else picked.values


def _subset(rows=(0, 2)):
    return CSAMPLES.subset(rows).targets


def _to(arg=torch.float32, what="trajectories"):
    whole = {"trajectories": CTRAJ.with_readout(READOUT), "controls": CONTROLS, "readout": READOUT}[what]
    out = whole.to(arg)
    return out.flat_states() if what == "trajectories" else out.values if what == "controls" else out.matrix


def _repeat(n=2):
    return CONTROLS.repeat(n).values


GRID = TIMES.expand(3, -1)
THETA, SCALE = torch.tensor([1.0], dtype=DT), torch.tensor([0.1], dtype=DT)
ONE_READING = {"t": {"a": 1.0}}


def _control_function(t=GRID, num_experiments=3, num_controls=1):
    function = tms.signals.Controls.from_function(lambda s: 0.1 * s.unsqueeze(-1), num_experiments, num_controls)
    return function.at(t)


def _known_rhs(y=Y0, t=0.0, u=U):
    return CHEMO.known_rhs(y, t, u) + CHEMO.true_rhs(y, t, u)


def _select_inputs(y=Y0, u=U):
    return CHEMO.select_inputs(y, u)


def _embed(f=Y0[:, :1]):
    return CHEMO.embed(f) + CHEMO.true_correction(torch.cat([Y0[:, :1], U], -1))


def _at(theta=(0.3,)):
    system = tms.MisspecifiedSystem(lambda y, th: -th[0] * y, 2, parameters={"k": (0.5, 0.1)})
    return system.at(theta).known_rhs(Y0)


def _fields(matrix=((0.0, 1.0), (-1.0, 0.0)), coef=0.5, positions=((0.0, 0.0),)):
    linear = tms.systems.LinearField(matrix)(Y0)
    gravity = tms.systems.PointMassGravity([1.0], positions)(Y0 + 2.0)
    return linear + tms.systems.QuadraticField(coef)(Y0) + gravity


def _simulate_controls(system=CHEMO, controls=CONTROLS, known_only=False, rtol=1e-10):
    return tms.simulate(system, Y0 + 1.0, TIMES, controls=controls, known_only=known_only, rtol=rtol).states


def _predict_controls(y0=Y0 + 1.0, controls=CONTROLS, atol=1e-9):
    return CMODEL.predict(y0, TIMES, controls=controls, solver=tms.Solver(atol=atol))


def _with_readout(readout=READOUT, readings=None, state_names=("a", "b")):
    return TRAJ.with_state_names(state_names).with_readout(readout, readings).readings


def _readout_names(weights=ONE_READING, state_names=("a", "b"), names=("b", "a")):
    readout = tms.Readout.from_weights(weights, state_names)
    return readout.for_states(names).matrix + len(readout.describe(names))


def _reordered(names=("b", "a"), initial_states=Y0):
    data = TRAJ.with_state_names(["a", "b"]).with_initial_states(initial_states)
    return data.reordered(names).flat_states()


def _save_columns(path=None, state_columns=None, control_columns=("u0",)):
    target = FILES / "columns.csv" if path is None else path
    CTRAJ.with_state_names(["y0", "y1"]).save(target, state_columns=state_columns)
    return tms.Trajectories.load(target, state_columns=state_columns, control_columns=control_columns).flat_states()


def _gp_settings(device="cpu", dtype=torch.float64):
    return (
        tms.CorrectionGP(device=device, dtype=dtype, **GP_HYPER).fit(SAMPLES.inputs, SAMPLES.targets).predict_mean(Y0)
    )


GP_HYPER = dict(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4)


def _posterior_object(targets=SAMPLES.targets, x=Y0):
    posterior = FITTED.posterior()
    return posterior.with_targets(targets).mean(Y0) + posterior.sd_ratio(x).sum()


def _map_tasks(fn=math.sqrt, tasks=(1.0, 4.0), each=None):
    return parallel_results(tms.parallel.map_tasks(fn, tasks, each=each))


def parallel_results(results):
    return torch.tensor([float(r) for r in results], dtype=DT)


def _parameter_helpers(theta=THETA, scale=SCALE, num_samples=3):
    jac = tms.parameters.jacobian(lambda th: Y0 * th[0], theta, scale)
    posterior = tms.parameters.ParameterPosterior.prior(tms.parameters.check_priors({"k": (1.0, 0.1)}), 3, 1, Y0)
    return jac.sum() + posterior.sample(num_samples, torch.Generator().manual_seed(0)).sum()


def _statistics(dim=0, dtype=torch.float64):
    mean, se = tms.metrics.mean_and_standard_error(torch.ones(3, 2, dtype=DT), dim)
    return mean.sum() + se.sum() + tms.metrics.box_grid(((0.0, 1.0),), 3, dtype=dtype)[1].sum()


#: independent computations of what some calls return (numpy), checked on every accepted argument
ORACLES = {}


CASES = [
    (_select, {"index": BAD_SELECTIONS, "what": ["trajectories", "controls"]}),
    (_subset, {"rows": BAD_SELECTIONS}),
    (_to, {"arg": BAD_DEVICES, "what": ["trajectories", "controls", "readout"]}),
    (_repeat, {"n": BAD_NUMBERS}),
    (_control_function, {"t": BAD_TIMES + BAD_ARRAYS, "num_experiments": BAD_NUMBERS, "num_controls": BAD_NUMBERS}),
    (_known_rhs, {"y": BAD_FINITE_ARRAYS, "t": BAD_NUMBERS + BAD_TIMES, "u": BAD_FINITE_ARRAYS}),
    (_select_inputs, {"y": BAD_FINITE_ARRAYS, "u": BAD_FINITE_ARRAYS}),
    (_embed, {"f": BAD_ARRAYS}),
    (_at, {"theta": BAD_ARRAYS + BAD_NUMBERS}),
    (_fields, {"matrix": BAD_ARRAYS, "coef": BAD_NUMBERS, "positions": BAD_ARRAYS}),
    (
        _simulate_controls,
        {
            "system": [None, "paper_linear", 3, SYSTEM],
            "controls": [None, CONTROLS[:2], LEVELS, "u", tms.signals.Controls(TIMES, LEVELS)],
            "known_only": [None, 1, "yes"],
            "rtol": BAD_NUMBERS,
        },
    ),
    (_predict_controls, {"y0": BAD_ARRAYS, "controls": [None, CONTROLS[:1], LEVELS, 3], "atol": BAD_NUMBERS}),
    (
        _with_readout,
        {
            "readout": [None, "t = a + b", 3, READOUT.to(torch.float32)],
            "readings": BAD_ARRAYS,
            "state_names": BAD_NAMES,
        },
    ),  # fmt: skip
    (
        _readout_names,
        {
            "weights": [{}, {"t": {"c": 1.0}}, {"t": {"a": 10**400}}, "t", {"t": 1.0}],
            "state_names": BAD_NAMES,
            "names": BAD_NAMES,
        },
    ),  # fmt: skip
    (_reordered, {"names": BAD_NAMES + [("a", "c")], "initial_states": BAD_ARRAYS}),
    (
        _save_columns,
        {
            "path": BAD_OUTPUTS[:3] + [str(FILES / "no" / "c.csv"), str(FILES)],
            "state_columns": BAD_NAMES,
            "control_columns": BAD_NAMES,
        },
    ),  # fmt: skip
    (_gp_settings, {"device": BAD_DEVICES, "dtype": BAD_DEVICES}),
    (_posterior_object, {"targets": BAD_ARRAYS, "x": BAD_FINITE_ARRAYS}),
    (_map_tasks, {"fn": [None, 3, lambda: 1.0], "tasks": [None, 3, "ab", []], "each": [3, lambda: None]}),
    (
        _parameter_helpers,
        {"theta": BAD_ARRAYS, "scale": BAD_ARRAYS + [torch.tensor([-1.0])], "num_samples": BAD_NUMBERS},
    ),  # fmt: skip
    (_statistics, {"dim": BAD_NUMBERS, "dtype": BAD_DEVICES}),
    (_simulate, {"y0": BAD_ARRAYS, "times": BAD_TIMES, "max_steps": BAD_NUMBERS}),
    (
        _samples,
        {
            "states": BAD_ARRAYS,
            "times": BAD_TIMES,
            "derivative": ["bogus", None, 3],
            "noise_std": BAD_NUMBERS,
            "order": BAD_NUMBERS,
            "window": BAD_NUMBERS,
            "degree": BAD_NUMBERS,
        },
    ),
    (
        _gp,
        {
            "lengthscale": BAD_NUMBERS,
            "outputscale": BAD_NUMBERS,
            "noise_variance": BAD_NUMBERS,
            "max_iter": BAD_NUMBERS,
            "degree": BAD_NUMBERS,
            "kernel": ["cubic", None, 3],
        },
    ),
    (_fit, {"inputs": BAD_ARRAYS, "targets": BAD_ARRAYS}),
    (_predict, {"x": BAD_ARRAYS}),
    (_predict_mean, {"x": BAD_ARRAYS}),
    (_ode, {"y0": BAD_ARRAYS, "times": BAD_TIMES, "max_steps": BAD_NUMBERS}),
    (_greedy, {"candidates": BAD_ARRAYS, "budget": BAD_NUMBERS, "times": BAD_TIMES, "method": ["bogus", None]}),
    (_random, {"candidates": BAD_ARRAYS, "budget": BAD_NUMBERS}),
    (_information, {"points": BAD_ARRAYS}),
    (_rmse, {"predicted": BAD_ARRAYS, "true": BAD_ARRAYS}),
    (_fd, {"states": BAD_ARRAYS, "times": BAD_TIMES, "order": BAD_NUMBERS}),
    (_grid, {"domain": BAD_ARRAYS + [((1.0, -1.0),), ((0.0, float("inf")),)], "size": BAD_NUMBERS}),
    (_trajectories, {"times": BAD_TIMES, "states": BAD_ARRAYS, "state_names": BAD_NAMES, "readings": BAD_ARRAYS}),
    (_readout, {"matrix": BAD_ARRAYS + [((0.0, 0.0),)], "names": BAD_NAMES}),
    (_parse, {"text": ["total", "= a", "total = c", "total = a b", "total = 1e999*a", "t = a + + b", "t = 2**3*a"]}),
    (_controls, {"knots": BAD_TIMES, "values": BAD_ARRAYS, "kind": ["bogus", None, 3]}),
    (
        _system,
        {
            "state_dim": BAD_NUMBERS,
            "correction_inputs": BAD_INDICES,
            "correction_outputs": BAD_INDICES,
            "domain": BAD_ARRAYS + [((1.0, -1.0),)],
        },
    ),
    (_smooth, {"states": BAD_ARRAYS, "times": BAD_TIMES, "window": BAD_NUMBERS, "degree": BAD_NUMBERS}),
    (_correction_error, {"domain": BAD_ARRAYS, "resolution": BAD_NUMBERS, "metric": ["bogus", None, 3]}),
    (_marginal_gains, {"indices": BAD_INDICES, "candidates": BAD_ARRAYS}),
    (_partitioned, {"partition": BAD_PARTITIONS, "capacities": BAD_CAPACITIES, "budget": BAD_NUMBERS}),
    (_sampling_times, {"initial_states": BAD_ARRAYS, "times": BAD_TIMES, "per_experiment": BAD_NUMBERS}),
    (_posterior, {"y0": BAD_ARRAYS, "times": BAD_TIMES, "num_samples": BAD_NUMBERS, "scale": BAD_NUMBERS}),
    (_mean_se, {"values": BAD_ARRAYS + [[], [float("nan")]]}),
    (_proxies, {"candidates": BAD_ARRAYS, "times": BAD_TIMES, "max_steps": BAD_NUMBERS}),
    (_variance_reduction, {"points": BAD_ARRAYS, "domain_size": BAD_NUMBERS}),
    (_agnostic, {"candidates": BAD_ARRAYS, "budget": BAD_NUMBERS, "times": BAD_TIMES}),
    (_uniform_box, {"n": BAD_NUMBERS, "domain": BAD_ARRAYS + [((1.0, -1.0),)]}),
    (_box_grid, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "resolution": BAD_NUMBERS}),
    (_integrated_error, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "resolution": BAD_NUMBERS}),
    (_campaign_ask, {"k": BAD_NUMBERS, "candidates": BAD_ARRAYS, "times": BAD_TIMES}),
    (_load_trajectories, {"path": BAD_FILES}),
    (_load_model, {"path": BAD_FILES}),
    (_campaign_load, {"path": BAD_FILES, "system": [None, "paper_linear", tms.systems.paper_gravity()]}),
    (_integrated_norm, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "resolution": BAD_NUMBERS}),
    (_integrate_over_box, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "resolution": BAD_NUMBERS, "chunk": BAD_NUMBERS}),
    (_mse, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "resolution": BAD_NUMBERS}),
    (_orbits, {"n": BAD_NUMBERS, "mass": BAD_NUMBERS, "half_width": BAD_NUMBERS, "min_radius": BAD_NUMBERS}),
    (_true_gain, {"indices": BAD_INDICES, "candidates": BAD_ARRAYS, "times": BAD_TIMES}),
    (_proxy_gap, {"indices": BAD_INDICES, "candidates": BAD_ARRAYS, "times": BAD_TIMES}),
    (_proxy_check, {"indices": BAD_INDICES, "candidates": BAD_ARRAYS, "proxy": ["bogus", None, 3]}),
    (
        _refine,
        {"initial_states": BAD_ARRAYS, "box": BAD_ARRAYS + [((1.0, -1.0),)], "steps": BAD_NUMBERS, "lr": BAD_NUMBERS},
    ),  # fmt: skip
    (_get_system, {"name": ["bogus", None, 3, "", "paper linear"]}),
    (_load_system, {"spec": ["bogus", None, 3, "", "os:system", "nowhere.py:f", "paper_linear:x", "a:b:c"]}),
    (_data_driven, {"system": [None, "paper_linear", 3]}),
    (_interval, {"level": BAD_NUMBERS + [1.0]}),
    (_read, {"readout": [None, "total = a + b", tms.Readout([[1.0, 1.0, 1.0]], ["t"]), 3]}),
    (_plot_trajectories, {"states": BAD_ARRAYS, "dims": BAD_DIMS, "path": BAD_OUTPUTS}),
    (_plot_design, {"candidates": BAD_ARRAYS, "picks": BAD_INDICES, "path": BAD_OUTPUTS}),
    (_plot_bands, {"true_states": BAD_ARRAYS, "index": BAD_NUMBERS, "levels": [(1.5,), (0.0,), "ab", None, ()]}),
    (_plot_curves, {"ks": BAD_ARRAYS + [(1, 2)], "curve": BAD_ARRAYS + [[0.1, -1.0, 0.0], (np.ones(3), -np.ones(3))]}),
    (_plot_calibration, {"nominal": BAD_ARRAYS + [(0.5, 2.0)], "empirical": BAD_ARRAYS + [(0.5,)]}),
    (_plot_error_map, {"domain": BAD_ARRAYS + [((1.0, -1.0),)], "traces": BAD_ARRAYS, "resolution": BAD_NUMBERS}),
    (
        _check_priors,
        {
            "parameters": [
                {"k": (1.0, -0.1)},
                {"k": (float("nan"), 0.1)},
                "k",
                3,
                [("k",)],
                {"k": 1.0},
                {3: (1.0, 0.1)},
                {"k": (1.0, 0.1, 2.0)},
                {"k": ("a", 0.1)},
                {"": (1.0, 0.1)},
                {"k": (True, 0.1)},
                {"k": (1.0, 1e-320)},
                {"k": (10**400, 1.0)},
                {},
            ]
        },
    ),
]


def _fit_correction(trajectories=TRAJ, gp=None, select="cv", derivative="auto", folds=3, refine=None):
    return tms.fit_correction(
        trajectories, SYSTEM, gp=gp, select=select, derivative=derivative, folds=folds, refine=refine, progress=False
    ).predict_mean(Y0)


def _fit_trajectories(trajectories=TRAJ, shooting="single", state_noise=None, max_iter=3, relevance=None):
    return tms.fit_trajectories(
        FITTED, SYSTEM, trajectories, shooting=shooting, state_noise=state_noise, max_iter=max_iter, relevance=relevance
    ).predict_mean(Y0)


def _calibrate(trajectories=TRAJ, level=0.9, folds=3, num_samples=4, state_noise="auto"):
    model = tms.CorrectedODE(SYSTEM, FITTED)
    return model.calibrate(
        trajectories, SAMPLES, level=level, folds=folds, num_samples=num_samples, state_noise=state_noise,
        progress=False,
    ).scale  # fmt: skip


BAD_TRAJECTORIES = [
    TRAJ.states,
    None,
    "data.csv",
    TRAJ[:1],
    tms.Trajectories(TIMES[:2], TRAJ.states[:, :2]),
    tms.Trajectories(TIMES, TRAJ.states * 1e200),
    tms.Trajectories(TIMES, TRAJ.states.clone().index_fill_(1, torch.tensor([2, 3, 4]), float("nan"))),
    tms.Trajectories(TIMES, torch.zeros(3, 6, 3, dtype=DT)),
]
#: the fits: each call takes a second or more, so they run in the slow tests
SLOW_CASES = [
    (
        _fit_correction,
        {
            "trajectories": BAD_TRAJECTORIES,
            "gp": ["rbf", 3, tms.CorrectionGP(kernel="polynomial", degree=2)],
            "select": ["bogus", None, 3],
            "derivative": ["bogus", None, 3],
            "folds": BAD_NUMBERS,
            "refine": ["yes", 2, 0.5],
        },
    ),
    (_campaign_tell, {"trajectories": BAD_TRAJECTORIES, "asked": BAD_INDICES}),
    (
        _fit_trajectories,
        {
            "trajectories": BAD_TRAJECTORIES,
            "shooting": ["bogus", None, 3],
            "state_noise": BAD_NUMBERS + [[1.0], [1.0, -1.0]],
            "max_iter": BAD_NUMBERS,
            "relevance": ["yes", 2],
        },
    ),
    (
        _calibrate,
        {
            "trajectories": BAD_TRAJECTORIES,
            "level": BAD_NUMBERS + [1.0],
            "folds": BAD_NUMBERS,
            "num_samples": BAD_NUMBERS,
            "state_noise": ["bogus", "-2%", -1.0, [1.0], float("nan")],
        },
    ),
]


ORACLES.update(
    {
        _rmse: (_rmse_oracle, 1e-9),
        _mean_se: (_mean_se_oracle, 1e-9),
        _information: (_information_oracle, 1e-9),
        _predict: (_posterior_oracle, 1e-8),
        _predict_mean: (lambda x=Y0: _posterior_oracle(x)[0], 1e-8),
        _fd: (_fd_oracle, 1e-9),
        _readout: (_readout_oracle, 1e-12),
        _parse: (_parse_oracle, 0.0),
        _grid: (_grid_oracle, 1e-12),
        _box_grid: (_box_grid_oracle, 1e-12),
        _controls: (_controls_oracle, 1e-12),
        _simulate: (_simulate_oracle, 1e-6),
        _integrate_over_box: (_integrate_oracle, 1e-12),
    }
)


def _every_case(cases=CASES):
    for call, args in cases:
        for name, values in args.items():
            for k, value in enumerate(values):
                yield pytest.param(call, name, value, id=f"{call.__name__}-{name}-{k}")


@st.composite
def two_bad_arguments(draw):
    """One call with two of its arguments changed at once (the long profile: interactions of the checks)."""
    call, args = draw(st.sampled_from(CASES))
    names = draw(st.lists(st.sampled_from(sorted(args)), min_size=1, max_size=2, unique=True))
    return call, {name: draw(st.sampled_from(args[name])) for name in names}


@pytest.mark.parametrize("call", [call for call, _ in CASES], ids=lambda call: call.__name__)
def test_every_valid_call_is_valid(call):
    """Each call as written (no argument changed) succeeds, with a finite result equal to its oracle's."""
    out = call()
    _no_nan(out)
    oracle, rtol = ORACLES.get(call, (None, None))
    if oracle is not None:
        _agrees(out, oracle(), rtol)


@pytest.mark.filterwarnings("ignore::torchmisspec.NumericalWarning")  # extreme values: warnings are honest
@pytest.mark.parametrize(("call", "name", "value"), list(_every_case()))
def test_one_bad_argument(call, name, value):
    """Every listed bad value of every argument, one at a time (all of them: a few seconds)."""
    _check(call, **{name: value})


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::torchmisspec.NumericalWarning", "ignore::torchmisspec.TorchMisspecWarning")
@pytest.mark.parametrize(("call", "name", "value"), list(_every_case(SLOW_CASES)))
def test_one_bad_argument_of_the_fits(call, name, value):
    """The fits (fit_correction, fit_trajectories, calibration), every listed bad value of every argument."""
    _check(call, **{name: value})


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::torchmisspec.NumericalWarning")  # extreme values: warnings are honest
@settings(max_examples=LONG_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(two_bad_arguments())
def test_two_bad_arguments_long(case):
    call, kwargs = case
    _check(call, **kwargs)
