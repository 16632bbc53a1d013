"""The solver's settings as one option object (:class:`torchmisspec.Solver`) for ``predict`` and ``posterior``."""

from __future__ import annotations

import dataclasses
import inspect

import pytest
import torch

import torchmisspec as tms
from torchmisspec._ode import solve
from torchmisspec.systems import LinearField, MisspecifiedSystem

DT = torch.float64

#: ``posterior(y0, times, num_samples=3, generator=torch.Generator().manual_seed(3), rtol=1e-4, atol=1e-6,
#: max_steps=500, scale=1.0)`` before the settings were grouped (torchmisspec at b3050ac): the last states of the
#: sampled paths (S, B, d) and of the mean paths (B, d)
BEFORE_SAMPLES = [
    [[-0.5605314160052027, -0.8998559512672456], [-0.35084224266998093, 0.28218581887639077]],
    [[-0.5605313377841227, -0.8998559592180444], [-0.3508421944483749, 0.2821857693068597]],
    [[-0.5605313660712412, -0.8998559018918516], [-0.35084220176950665, 0.2821858157736998]],
]
BEFORE_MEAN = [[-0.5605313774952525, -0.8998559341446809], [-0.3508422149909646, 0.28218581167106277]]


@pytest.fixture(scope="module")
def model():
    """A damped oscillator with an affine correction learned by a degree-1 polynomial kernel."""
    A = torch.tensor([[0.0, 1.0], [-1.0, -0.1]], dtype=DT)
    system = MisspecifiedSystem(LinearField(A), 2, known_matrix=A, name="oscillator")
    X = torch.rand(20, 2, generator=torch.Generator().manual_seed(0), dtype=DT) * 2 - 1
    Y = X @ torch.tensor([[0.0, 0.0], [-0.2, 0.1]], dtype=DT).T + 0.01
    return tms.CorrectedODE(system, tms.CorrectionGP(kernel="polynomial", degree=1).fit(X, Y))


def test_the_defaults_are_the_solves_defaults():
    solver = tms.Solver()
    defaults = {k: p.default for k, p in inspect.signature(solve).parameters.items()}
    assert solver.keywords() == {k: defaults[k] for k in ("method", "rtol", "atol", "options", "max_steps")}
    assert solver == tms.Solver(method="dopri5", rtol=1e-7, atol=1e-9, max_steps=None, options=None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        solver.rtol = 1e-3


def test_a_posterior_with_settings_has_the_numbers_of_the_keywords_it_replaces(model, one_thread):
    y0, times = torch.tensor([[1.0, 0.0], [0.0, -0.5]], dtype=DT), torch.linspace(0, 2, 5, dtype=DT)
    solver = tms.Solver(rtol=1e-4, atol=1e-6, max_steps=500)
    kw = dict(num_samples=3, scale=1.0)
    post = model.posterior(y0, times, generator=torch.Generator().manual_seed(3), solver=solver, **kw)
    torch.testing.assert_close(post.samples[:, :, -1], torch.tensor(BEFORE_SAMPLES, dtype=DT), rtol=1e-9, atol=0)
    torch.testing.assert_close(post.mean_path[:, -1], torch.tensor(BEFORE_MEAN, dtype=DT), rtol=1e-9, atol=0)
    assert torch.equal(post.mean_path, model.predict(y0, times, solver=solver))
    default = model.posterior(y0, times, generator=torch.Generator().manual_seed(3), **kw)
    assert not torch.equal(default.mean_path, post.mean_path)  # the settings are used


def test_bad_settings_are_refused_with_the_fix(model):
    with pytest.raises(tms.InputError, match=r"rtol: expected a tolerance below 1 .*got 2"):
        tms.Solver(rtol=2.0)
    with pytest.raises(tms.InputError, match=r"max_steps: expected an integer >= 1, got 0"):
        tms.Solver(max_steps=0)
    with pytest.raises(tms.InputError, match=r"options: expected a dict of torchdiffeq solver options"):
        tms.Solver(options="x")
    y0, times = torch.zeros(1, 2, dtype=DT), torch.linspace(0, 1, 3, dtype=DT)
    said = r"solver: expected a torchmisspec.Solver .* or None, got \{'rtol': 1e-06\} \(dict\); pass solver=tms"
    with pytest.raises(tms.InputError, match=said.replace("tms", r"torchmisspec.Solver\(\*\*settings\)")):
        model.predict(y0, times, solver={"rtol": 1e-6})
    with pytest.raises(tms.InputError, match=r"solver: expected a torchmisspec.Solver .* got 'rk4' \(str\)"):
        model.posterior(y0, times, num_samples=2, scale=1.0, solver="rk4")


def test_options_are_copied():
    options = {"step_size": 0.1}
    solver = tms.Solver(method="rk4", options=options)
    options["step_size"] = 1.0
    assert solver.options == {"step_size": 0.1}
