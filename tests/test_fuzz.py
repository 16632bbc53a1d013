"""Property-based fuzz of the public API: each case changes ONE argument of a valid call to a bad value.

The promise checked: the call either returns a result without NaN/inf, or raises a ``TorchMisspecError`` (a plain
``TypeError`` is accepted for a value of the wrong Python type, as Python itself does), within a time bound. The
default run draws a few hundred cases; ``-m slow`` runs a longer profile.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchmisspec as tms

DT = torch.float64
SYSTEM = tms.systems.paper_linear()
TIMES = torch.linspace(0.0, 6.0, 6, dtype=DT)
Y0 = torch.tensor([[0.5, -0.3], [0.2, 0.7], [-0.6, 0.1]], dtype=DT)
TRAJ = tms.simulate(SYSTEM, Y0, TIMES)
SAMPLES = tms.correction_samples(TRAJ, SYSTEM, derivative="oracle", noise_std=1e-3, generator=torch.Generator())
PRIOR = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4)
FITTED = tms.CorrectionGP(lengthscale=1.0, outputscale=4e-5, noise_variance=1e-4).fit(SAMPLES.inputs, SAMPLES.targets)
CANDIDATES = tms.design.candidates.grid(SYSTEM.domain, 4)
TIME_BOUND = 20.0  # seconds per call, on a loaded 2-core machine

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
]
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
    elif hasattr(out, "__dataclass_fields__") and not isinstance(out, tms.design.DesignResult):
        for name in out.__dataclass_fields__:
            _no_nan(getattr(out, name))
    elif isinstance(out, tms.design.DesignResult):
        _no_nan(out.indices.double())
        _no_nan(out.points)


def _check(call, **kwargs) -> None:
    start = time.perf_counter()
    try:
        out = call(**kwargs)
    except tms.TorchMisspecError:
        pass
    except TypeError as exc:  # a wrong Python type; must not come from deep inside torch for a valid type
        assert "unexpected keyword" not in str(exc)
    else:
        _no_nan(out)
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
    return FITTED.predict(x)


def _predict_mean(x=Y0):
    return FITTED.predict_mean(x)


def _ode(y0=Y0[:2], times=TIMES, max_steps=2000):
    return tms.CorrectedODE(SYSTEM, FITTED).predict(y0, times, max_steps=max_steps)


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


CASES = [
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
]


@st.composite
def one_bad_argument(draw):
    call, args = draw(st.sampled_from(CASES))
    name = draw(st.sampled_from(sorted(args)))
    value = draw(st.sampled_from(args[name]))
    return call, name, value


def test_every_valid_call_is_valid():
    for call, _ in CASES:
        _no_nan(call())


@pytest.mark.filterwarnings("ignore::torchmisspec.NumericalWarning")  # extreme values: warnings are honest
@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(one_bad_argument())
def test_one_bad_argument(case):
    call, name, value = case
    _check(call, **{name: value})


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::torchmisspec.NumericalWarning")  # extreme values: warnings are honest
@settings(max_examples=1500, deadline=None, suppress_health_check=list(HealthCheck))
@given(one_bad_argument())
def test_one_bad_argument_long(case):
    call, name, value = case
    _check(call, **{name: value})
