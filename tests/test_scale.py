"""The default fit in the data's own units (issue 40 item 7; issue 41 item 3): states scaled by c give predictions
scaled by c, states scaled by different factors give each component's prediction scaled by its own, and the model
fitted on scaled data is an ordinary model in the user's units (saved and loaded as any other).

The case of the issue: ``paper_linear``, 6 experiments x 11 times, 1 % multiplicative noise, states and G scaled by c.
Before the fix the refinement through the ODE raised IntegrationError at c = 1e-3, and the other scales' predictions
differed from c = 1's by up to 1.6e-5 (relative).
"""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._rescale import rescaled
from torchmisspec.learning._units import data_units

DT = torch.float64
TOLERANCE = 1e-4  # the issue's goal: max |pred_c / c - pred_1| / max |pred_1|


def scaled_system(scales) -> tms.MisspecifiedSystem:
    """paper_linear's G for states y = S z (z the paper's states): y' = S A S^-1 y."""
    base = tms.systems.paper_linear()
    S = torch.tensor(scales, dtype=DT)
    B = base.known_matrix * S.unsqueeze(-1) / S.unsqueeze(0)
    domain = [(lo * s, hi * s) for (lo, hi), s in zip(base.domain, scales, strict=True)]
    return tms.MisspecifiedSystem(lambda y: y @ B.T, 2, name="scaled", domain=domain)


def lab(scales, seed=0):
    """The issue's data in units ``scales`` (one factor per state): times, states, initial states."""
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(seed)
    times = torch.linspace(0, 6, 11, dtype=DT)
    y0 = tms.design.candidates.uniform_box(6, system.domain, generator=g)
    states = tms.simulate(system, y0, times).states
    noisy = states * (1 + 0.01 * torch.randn(states.shape, generator=g, dtype=DT))
    S = torch.tensor(scales, dtype=DT)
    return times, noisy * S, y0 * S


def fit_and_predict(scales):
    times, states, y0 = lab(scales)
    system = scaled_system(scales)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)  # 6 experiments: "not significant", at every scale
        gp = tms.fit_correction(tms.Trajectories(times, states), system, progress=False)
    return gp, tms.CorrectedODE(system, gp).predict(y0[:3], times)


@pytest.fixture(scope="module")
def reference():
    return fit_and_predict([1.0, 1.0])


def relative(pred: torch.Tensor, ref: torch.Tensor) -> float:
    return float((pred - ref).abs().max() / ref.abs().max())


@pytest.mark.parametrize(
    "c", [1e-3, pytest.param(1e-2, marks=pytest.mark.slow), pytest.param(1e2, marks=pytest.mark.slow), 1e3]
)
def test_predictions_scale_with_the_states(reference, c):
    gp1, pred1 = reference
    gp, pred = fit_and_predict([c, c])
    assert gp.kernel == gp1.kernel == "features"
    assert relative(pred / c, pred1) <= TOLERANCE
    # the same terms, their coefficients in the user's units (a monomial of degree k: c^(1 - k))
    terms1, terms = gp1.terms(), gp.terms()
    assert [(t.output, t.name) for t in terms] == [(t.output, t.name) for t in terms1]
    for t, t1 in zip(terms, terms1, strict=True):
        factor = c ** (1 - degree(t.name))  # far below each coefficient's own uncertainty
        assert abs(t.mean - t1.mean * factor) <= 1e-2 * t1.std * factor and t.std == pytest.approx(
            t1.std * factor, 1e-2
        )


def degree(name: str) -> int:
    """A monomial's total degree from its name (``"1"``, ``"x1"``, ``"x1 x2^2"``)."""
    return 0 if name == "1" else sum(int(f.split("^")[1]) if "^" in f else 1 for f in name.split())


def test_states_of_very_different_scales_are_each_fitted_in_their_own(reference):
    """State 0 in units 1e3 times smaller, state 1 in units 100 times larger (G rewritten): each component's
    prediction is the unscaled one's in its own units, so it is as accurate relative to its scale."""
    _, pred1 = reference
    scales = [1e3, 1e-2]
    gp, pred = fit_and_predict(scales)
    S = torch.tensor(scales, dtype=DT)
    assert gp.kernel == "features"
    for j in range(2):
        assert relative(pred[..., j] / S[j], pred1[..., j]) <= TOLERANCE
    times, _, y0 = lab([1.0, 1.0])
    truth = tms.simulate(tms.systems.paper_linear(), y0[:3], times).states
    for j in range(2):  # as accurate as the unscaled fit, per component (each about 0.5 % of its range)
        assert relative(pred[..., j] / S[j], truth[..., j]) <= 1.01 * relative(pred1[..., j], truth[..., j])


def test_a_model_fitted_on_scaled_data_is_saved_and_loaded_in_the_users_units(tmp_path):
    times, states, y0 = lab([1e-3, 1e-3])
    system = scaled_system([1e-3, 1e-3])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        gp = tms.fit_correction(tms.Trajectories(times, states), system, progress=False, refine=False)
    assert gp.train_inputs_.abs().max() < 1e-2  # the user's units: inputs are states of size 1e-3
    path = gp.save(tmp_path / "scaled.pt")
    back = tms.CorrectionGP.load(path)
    x = states[0, :4]
    assert torch.equal(back.predict_mean(x), gp.predict_mean(x))
    before = tms.CorrectedODE(system, gp).predict(y0[:2], times)
    assert torch.equal(tms.CorrectedODE(system, back).predict(y0[:2], times), before)


def test_the_data_units_are_powers_of_ten_and_leave_data_of_order_one_alone():
    times, states, _ = lab([1.0, 1.0])
    assert data_units(tms.Trajectories(times, states)).trivial  # paper_linear's states: rms 0.58 and 0.43
    units = data_units(tms.Trajectories(times, states * torch.tensor([3e3, 2e-2], dtype=DT)))
    assert units.state.tolist() == [1e3, 1e-2]
    partly = states * torch.tensor([2e-2, 1.0], dtype=DT)
    partly[:, 1:, 1] = float("nan")
    partly[:, 0, 1] = 0.0  # never measured, known to start at 0: the other component's scale
    assert data_units(tms.Trajectories(times, partly)).state.tolist() == [1e-2, 1e-2]


@pytest.mark.parametrize(
    ("kernel", "options", "s_in", "s_out", "per_output"),
    [
        ("rbf", {}, [1e3, 1e3], [1e-2, 1e-2], False),
        ("rbf", {}, [1.0, 1.0], [1e3, 1e-2], True),  # a shared kernel, outputs in different units: one per output
        ("features", {"degree": 3}, [1e3, 1e-2], [1e3, 1e-2], True),
        ("features", {"degree": 2, "per_output": True}, [1e-3, 1e2], [1.0, 1e-3], True),
        ("features+rbf", {"degree": 2}, [1e2, 1e2], [1e-1, 1e-1], False),
        ("rbf", {}, [1e3, 1e-2], [1.0, 1.0], False),  # inputs in different units: the kernel's input_scale
        ("matern52", {"per_output": True}, [1e-3, 1e2], [1e2, 1e-3], True),
    ],
)
def test_a_fitted_model_is_rewritten_exactly_in_other_units(kernel, options, s_in, s_out, per_output):
    g = torch.Generator().manual_seed(3)
    X = 2 * torch.rand(50, 2, generator=g, dtype=DT) - 1
    Y = torch.stack([X[:, 0] ** 2 - X[:, 1], 0.5 * X[:, 0] * X[:, 1]], -1) + 0.01 * torch.randn(50, 2, generator=g)
    noise = torch.full((50, 2), 1e-4, dtype=DT)
    gp = tms.CorrectionGP(kernel=kernel, **options).fit(X, Y, noise=noise)
    s_in, s_out = torch.tensor(s_in, dtype=DT), torch.tensor(s_out, dtype=DT)
    new = rescaled(gp, s_in, s_out)
    assert new.per_output is per_output
    x = 2 * torch.rand(9, 2, generator=g, dtype=DT) - 1
    before, after = gp.predict(x), new.predict(x * s_in)
    assert torch.allclose(after.mean / s_out, before.mean, rtol=1e-7, atol=1e-9 * float(before.mean.abs().max()))
    assert torch.allclose(after.variance / s_out**2, before.variance, rtol=1e-6, atol=1e-12)
    assert torch.equal(new.train_noise_, noise * s_out**2)


def test_a_model_without_an_exact_form_in_other_units_is_not_rewritten():
    g = torch.Generator().manual_seed(5)
    X = torch.rand(20, 2, generator=g, dtype=DT)
    Y = X.sum(-1, keepdim=True) + 0.01 * torch.randn(20, 1, generator=g, dtype=DT)
    ones = torch.ones(1, dtype=DT)
    both = tms.CorrectionGP(kernel="features+rbf").fit(X, Y)
    assert rescaled(both, torch.tensor([1e3, 1e-2], dtype=DT), ones) is None  # its RBF part: one lengthscale
    polynomial = tms.CorrectionGP(kernel="polynomial").fit(X, Y)
    assert rescaled(polynomial, torch.tensor([10.0, 10.0], dtype=DT), ones) is None  # (1 + <x, x'>)^m
    assert rescaled(polynomial, torch.ones(2, dtype=DT), 10 * ones) is not None  # the outputs alone: exact


def test_a_kernels_input_scale_is_saved_with_the_model(tmp_path):
    X = torch.rand(20, 2, generator=torch.Generator().manual_seed(6), dtype=DT) * torch.tensor([1e3, 1e-2], dtype=DT)
    gp = tms.CorrectionGP(kernel=tms.gp.RBF(input_scale=[1e3, 1e-2])).fit(X, X[:, :1] / 1e3)
    back = tms.CorrectionGP.load(gp.save(tmp_path / "scaled.pt"))
    assert back.kernel_spec == tms.gp.RBF(input_scale=(1e3, 1e-2)) and back.clone().kernel_spec == back.kernel_spec
    assert torch.equal(back.predict(X[:3]).variance, gp.predict(X[:3]).variance)
    with pytest.raises(tms.InputError, match=r"input_scale: expected one positive finite number per input"):
        tms.gp.RBF(input_scale=[1.0, 0.0])


A_PK = torch.tensor([[-0.8, 0.2], [0.5, -0.2]], dtype=DT)  # two compartments, a saturable elimination missing


def pk_fit_and_predict(scales):
    """A fully measured two-compartment model whose F (on the central compartment, of both) is a saturation: the
    cross-validation chooses an RBF on two inputs, here in units ``scales``."""
    S = torch.tensor(scales, dtype=DT)
    B = A_PK * S.unsqueeze(-1) / S.unsqueeze(0)
    system = tms.MisspecifiedSystem(lambda y: y @ B.T, 2, correction_inputs=[0, 1], correction_outputs=[0])
    saturation = lambda x: (-0.8 * x[..., 0] / (0.5 + x[..., 0])).unsqueeze(-1)  # noqa: E731
    truth = tms.MisspecifiedSystem(
        lambda y: y @ A_PK.T, 2, correction=saturation, correction_inputs=[0], correction_outputs=[0]
    )
    g = torch.Generator().manual_seed(0)
    y0 = torch.stack([0.5 + 3.5 * torch.rand(6, generator=g, dtype=DT), 0.5 * torch.rand(6, generator=g, dtype=DT)], -1)
    t = torch.linspace(0, 8, 15, dtype=DT)
    y = tms.simulate(truth, y0, t).states
    y = y * (1 + 0.02 * torch.randn(y.shape, generator=g, dtype=DT))
    gp = tms.fit_correction(tms.Trajectories(t, y * S), system, progress=False)
    return gp, tms.CorrectedODE(system, gp).predict(y0[:3] * S, t) / S


def test_an_rbf_on_inputs_of_different_scales_sees_them_standardized():
    gp1, pred1 = pk_fit_and_predict([1.0, 1.0])
    gp, pred = pk_fit_and_predict([1e3, 1e-2])
    assert gp1.kernel_spec == tms.gp.RBF() and gp.kernel_spec == tms.gp.RBF(input_scale=(1e3, 1e-2))
    assert gp.lengthscale == pytest.approx(gp1.lengthscale, rel=1e-6)
    for j in range(2):
        assert relative(pred[..., j], pred1[..., j]) <= TOLERANCE


@pytest.mark.slow
def test_the_refinement_through_the_ode_scales_with_the_states():
    """fit_trajectories on its own (as a calibration's folds call it) at c = 1e-3: it raised IntegrationError."""
    out = {}
    for c in (1.0, 1e-3):
        times, states, _ = lab([c, c])
        data = tms.Trajectories(times, states)
        system = scaled_system([c, c])
        samples = tms.correction_samples(data, system)
        gp = tms.CorrectionGP(kernel="features", degree=3, per_output=True).fit(samples)
        refined = tms.fit_trajectories(gp, system, data, state_noise=(0.01 * c) ** 2)
        assert refined.refinement_["state_noise"] == pytest.approx((0.01 * c) ** 2)
        out[c] = refined.predict_mean(states[0]) / c
    assert relative(out[1e-3], out[1.0]) <= TOLERANCE


@pytest.mark.parametrize("scales", [[1e3, 1e3], [1e3, 1.0]])
def test_the_cross_validations_lengthscales_are_in_the_users_units(scales, reference):
    """The candidates are compared in the data's units; their record names lengthscales in the user's (a CLI user
    read 'chose rbf lengthscale=0.04322' beside a model of lengthscale 4.322): the chosen RBF's lengthscale and the
    label agree with the model saved, and the scores stay the ones compared."""
    gp, _ = fit_and_predict(scales)
    cv, cv1 = gp.cross_validation_, reference[0].cross_validation_
    assert cv.scores == pytest.approx(cv1.scores, rel=1e-9) and cv.index == cv1.index
    if scales[0] == scales[1]:  # one input scale: the lengthscales times it, the labels with them
        for e, e1 in zip(cv.lengthscales, cv1.lengthscales, strict=True):
            assert (e is None and e1 is None) or e == pytest.approx(e1 * scales[0], rel=1e-12)
        if gp.kernel == "rbf":
            assert float(gp.lengthscale) == pytest.approx(cv.best_lengthscale, rel=1e-12)
            assert cv.best == f"rbf lengthscale={cv.best_lengthscale:.4g}"
    else:  # inputs of different scales: the lengthscales stay in the data's units, and the labels say so
        assert cv.lengthscales == cv1.lengthscales
        assert all(
            c.endswith("(in the data's units)") for c, e in zip(cv.candidates, cv.lengthscales, strict=True) if e
        )
