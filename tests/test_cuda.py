"""The whole package on a GPU (issue 26): fit, predict, posterior bands, calibration, design, Campaign and save/load
with every tensor on CUDA, each checked against the same call on the CPU.

Skipped where CUDA is not available (CI has no GPU). ``TORCHMISSPEC_TEST_DEVICE=cpu`` runs the same tests with the CPU
as the "device" (both sides on the CPU), which checks the tests themselves on a machine without a GPU.
"""

from __future__ import annotations

import os
import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design

DEVICE = os.environ.get("TORCHMISSPEC_TEST_DEVICE", "cuda")
DT = torch.float64
pytestmark = pytest.mark.skipif(
    DEVICE == "cuda" and not torch.cuda.is_available(),
    reason="CUDA is not available (TORCHMISSPEC_TEST_DEVICE=cpu checks these tests on the CPU)",
)


def _on_device(t: torch.Tensor) -> bool:
    return t.device.type == torch.device(DEVICE).type


def _close(a: torch.Tensor, b: torch.Tensor, rtol: float = 1e-6, atol: float = 1e-9) -> None:
    assert _on_device(a), f"expected a tensor on {DEVICE}, got one on {a.device}"
    torch.testing.assert_close(a.cpu(), b.cpu(), rtol=rtol, atol=atol)


def _samples(system, n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(system.domain, dtype=DT).T
    x = lo + (hi - lo) * torch.rand(n, system.input_dim, generator=g, dtype=DT)
    f = system.true_correction(x)
    return x, f + 1e-3 * f.abs().max() * torch.randn(f.shape, generator=g, dtype=DT)


@pytest.fixture(scope="module")
def lab():
    """A small lab data set on the paper's linear system: 6 experiments of 11 times, 0.5 % noise."""
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(3)
    times = torch.linspace(0.0, 6.0, 11, dtype=DT)
    y0 = design.candidates.uniform_box(6, system.domain, generator=g)
    clean = tms.simulate(system, y0, times)
    return system, tms.Trajectories(times, clean.states * (1 + 0.005 * torch.randn(clean.states.shape, generator=g)))


@pytest.mark.parametrize("exact", [True, False], ids=["exact", "features"])
def test_fit_and_predict_follow_the_device(exact):
    """At given hyperparameters the posterior on the device is the CPU's to rounding; fitted, the device reaches the
    CPU's marginal likelihood and error of F (its flat optimum in the lengthscale lets the two stop apart)."""
    system = tms.systems.paper_linear()
    x, y = _samples(system, 400)
    grid = design.candidates.grid(system.domain, 9)
    given = dict(lengthscale=0.7, outputscale=1e-4, noise_variance=1e-7, exact=exact)
    cpu = tms.CorrectionGP(**given).fit(x, y)
    dev = tms.CorrectionGP(**given, device=DEVICE).fit(x.to(DEVICE), y.to(DEVICE))
    assert dev.device.type == torch.device(DEVICE).type
    post_cpu, post_dev = cpu.predict(grid), dev.predict(grid.to(DEVICE))
    scale = float(post_cpu.mean.abs().max())
    _close(post_dev.mean, post_cpu.mean, rtol=1e-6, atol=1e-8 * scale)
    _close(post_dev.variance, post_cpu.variance, rtol=1e-4, atol=1e-8 * float(post_cpu.variance.max()))
    # corrected trajectories and posterior draws: on the device, and the same mean as the CPU's
    y0 = grid[::10]
    times = torch.linspace(0.0, 6.0, 13, dtype=DT)
    pred_cpu = tms.CorrectedODE(system, cpu).predict(y0, times)
    pred_dev = tms.CorrectedODE(system, dev).predict(y0.to(DEVICE), times.to(DEVICE))
    _close(pred_dev, pred_cpu, rtol=1e-5, atol=1e-8)
    bands = tms.CorrectedODE(system, dev).posterior(
        y0.to(DEVICE), times.to(DEVICE), num_samples=32, generator=torch.Generator(DEVICE).manual_seed(0), scale=1.0
    )
    lower, upper = bands.interval(0.9)
    assert _on_device(lower) and bool(torch.isfinite(upper).all()) and bool((lower <= upper).all())

    cpu = tms.CorrectionGP(exact=exact).fit(x, y)
    dev = tms.CorrectionGP(exact=exact, device=DEVICE).fit(x.to(DEVICE), y.to(DEVICE))
    lml_cpu, lml_dev = float(cpu.log_marginal_likelihood_), float(dev.log_marginal_likelihood_)
    # in feature space the features are chosen for the fitted hyperparameters (a discrete choice): hyperparameters
    # that stop a little apart may take different features (on an H200: 7,967.9 against the CPU's 7,964.7)
    assert lml_dev == pytest.approx(lml_cpu, rel=1e-4 if exact else 1e-3, abs=1e-3)
    assert tms.correction_error(dev, system) == pytest.approx(tms.correction_error(cpu, system), rel=0.05)


def test_the_whole_loop_on_the_device(lab, tmp_path):
    """fit_correction with defaults, calibration, bands, design and a Campaign round, all on the device."""
    system, observed = lab
    data = observed.to(device=DEVICE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(data, system, progress=False)
        ref = tms.fit_correction(observed, system, progress=False)
    assert gp.device.type == torch.device(DEVICE).type, "the default model must follow the data's device"
    assert gp.kernel == ref.kernel
    assert tms.correction_error(gp, system) == pytest.approx(tms.correction_error(ref, system), rel=0.25)
    grid = design.candidates.grid(system.domain, 7)
    same = tms.CorrectionGP.load(gp.save(tmp_path / "fitted.pt"), device="cpu")  # the device's GP, on the CPU
    _close(gp.predict_mean(grid.to(DEVICE)), same.predict_mean(grid), rtol=1e-6, atol=1e-12)

    model = tms.CorrectedODE(system, gp)
    calibration = model.calibrate(data, progress=False)
    assert calibration.scale > 0
    times = observed.times.to(DEVICE)
    bands = model.posterior(data.states[:3, 0], times, num_samples=32, generator=torch.Generator(DEVICE).manual_seed(0))
    assert _on_device(bands.interval(0.9)[0])

    candidates = design.candidates.grid(system.domain, 8).to(DEVICE)
    for method in ("lazy", "stochastic"):  # the same draws (one CPU generator) on both: the same gains
        draws = (lambda: {"generator": torch.Generator().manual_seed(0)}) if method == "stochastic" else dict
        plan = design.greedy(candidates, 3, system=system, times=times, gp=gp, method=method, **draws())
        on_cpu = design.greedy(candidates.cpu(), 3, system=system, times=times.cpu(), gp=same, method=method, **draws())
        assert plan.information_gain == pytest.approx(on_cpu.information_gain, rel=1e-6)
    gpu_draws = torch.Generator(DEVICE).manual_seed(0)  # a generator on the device draws there
    plan = design.greedy(
        candidates,
        3,
        system=system,
        times=times,
        gp=gp,
        method="stochastic",
        engine=design.Engine(generator=gpu_draws),
    )
    assert len(set(plan.indices.tolist())) == 3

    campaign = design.Campaign(system, candidates, times, gp)
    asked = campaign.ask(2)
    assert _on_device(asked)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        refit = campaign.tell(tms.simulate(system, asked, times))
    assert refit.device.type == torch.device(DEVICE).type
    assert campaign.ask(1).shape == (1, 2)
    campaign.save(tmp_path / "campaign.pt")
    assert design.Campaign.load(tmp_path / "campaign.pt", system).num_experiments == campaign.num_experiments

    path = gp.save(tmp_path / "model.pt")  # saved on the device, loaded on the CPU and back
    on_cpu = tms.CorrectionGP.load(path, device="cpu")
    assert on_cpu.device.type == "cpu"
    back = tms.CorrectionGP.load(path, device=DEVICE)
    _close(back.predict_mean(grid.to(DEVICE)), on_cpu.predict_mean(grid), rtol=1e-8)


def test_a_large_fit_on_the_device():
    """Above LARGE_N samples the default GP fits in a feature space: on the device too, with the CPU's error."""
    from torchmisspec.gp._large import LARGE_N

    system = tms.systems.paper_linear()
    x, y = _samples(system, LARGE_N + 1000)
    dev = tms.CorrectionGP(device=DEVICE).fit(x.to(DEVICE), y.to(DEVICE))
    cpu = tms.CorrectionGP().fit(x, y)
    assert dev.approximation is not None and dev.approximation["kind"] == cpu.approximation["kind"]
    e_dev = tms.correction_error(dev, system)
    e_cpu = tms.correction_error(cpu, system)
    assert e_dev == pytest.approx(e_cpu, rel=0.05)
    draws = tms.CorrectedODE(system, dev).posterior(
        x[:4].to(DEVICE), torch.linspace(0, 3, 7, dtype=DT, device=DEVICE), num_samples=8, scale=1.0
    )
    assert _on_device(draws.samples) and bool(torch.isfinite(draws.samples).all())
