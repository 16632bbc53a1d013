"""Each reproducer of issue 25 ("hard to break, part two"), as reported, now gives a clear package error naming what
was expected and what was received, or a correct result. The classes are fixed where they arise (one check each in
``_validation``, ``design._common``, the file readers); this file keeps the reported cases together."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchmisspec as tms
from torchmisspec import design

DT = torch.float64


@pytest.fixture(scope="module")
def fitted():
    system = tms.systems.paper_linear()
    y0 = tms.design.candidates.grid(system.domain, 3)
    times = torch.linspace(0, 6, 6, dtype=DT)
    s = tms.correction_samples(tms.simulate(system, y0, times), system, derivative="oracle")
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4, noise_variance=1e-4).fit(s.inputs, s.targets)
    candidates = tms.design.candidates.grid(system.domain, 3)[:6]
    return system, gp, candidates, times


# ------------------------------------------------------------------------------ arguments silently converted
@pytest.mark.parametrize("indices", [[0.7], [True, False], torch.tensor([0.0, 1.0])])
def test_marginal_gains_refuses_non_integer_indices(fitted, indices):
    system, gp, candidates, times = fitted
    with pytest.raises(tms.InputError, match=r"indices: expected a sequence of integers, got"):
        design.marginal_gains(indices, candidates, system=system, times=times, gp=gp)


def test_marginal_gains_keeps_repeats_and_integer_types(fitted):
    system, gp, candidates, times = fitted
    a = design.marginal_gains([1, 1, 4], candidates, system=system, times=times, gp=gp)
    b = design.marginal_gains(np.array([1, 1, 4]), candidates, system=system, times=times, gp=gp)
    assert torch.equal(a, b) and a.shape == (3,)


@pytest.mark.parametrize("method", ["greedy", "agnostic", "random"])
@pytest.mark.parametrize(
    ("partition", "capacities", "said"),
    [
        (["a", "b"] * 3, [1, 1], "partition: expected an integer region label per candidate, got ['a', 'b'"),
        ([True, False] * 3, [1, 1], "partition: expected integer region labels, got dtype bool"),
        ([0.5, 1.0] * 3, [1, 1], "partition: expected integer region labels, got dtype float"),
        ([0, 1] * 3, {True: 1, 0: 1}, "capacities: expected integer region labels as keys, got True"),
    ],
)
def test_partitions_of_the_wrong_kind_are_refused(fitted, method, partition, capacities, said):
    system, gp, candidates, times = fitted
    kwargs = dict(system=system, times=times) | ({} if method == "random" else dict(gp=gp))
    with pytest.raises(tms.InputError) as info:
        getattr(design, method)(candidates, 2, partition=design.Partition(partition, capacities), **kwargs)
    assert said in str(info.value)


@pytest.mark.parametrize("method", ["greedy", "agnostic", "random"])
def test_a_capacity_beyond_the_candidates_limits_nothing(fitted, method):
    system, gp, candidates, times = fitted
    kwargs = dict(system=system, times=times, gp=gp)
    if method == "random":
        kwargs["generator"] = torch.Generator().manual_seed(0)
    huge = getattr(design, method)(candidates, 3, partition=design.Partition([0, 1] * 3, [10**30, 1]), **kwargs)
    if method == "random":
        kwargs["generator"] = torch.Generator().manual_seed(0)
    plain = getattr(design, method)(candidates, 3, partition=design.Partition([0, 1] * 3, [6, 1]), **kwargs)
    assert torch.equal(huge.indices, plain.indices)


def test_random_checks_the_proxies_shape(fitted):
    system, gp, candidates, times = fitted
    with pytest.raises(tms.ShapeError, match=r"proxies: expected shape \(6, T, 2\) to match the candidates"):
        design.random(candidates, 2, system=system, times=times, gp=gp, proxies=torch.zeros(2, 6, 2, dtype=DT))
    with pytest.raises(tms.ShapeError, match=r"proxies: expected one proxy trajectory per candidate \(6\), got 2"):
        design.random(candidates, 2, proxies=torch.zeros(2, 6, 2, dtype=DT))


# ------------------------------------------------------------------------------------ options of the wrong type
def test_solver_options_must_be_a_dict(fitted):
    system, gp, candidates, times = fitted
    with pytest.raises(tms.InputError, match=r"options: expected a dict of torchdiffeq solver options .* got 'x'"):
        tms.CorrectedODE(system, gp).predict(candidates[:2], times, solver=tms.Solver(options="x"))


@pytest.mark.parametrize(
    ("device", "said"),
    [(3, "got 3 (int)"), ("bogus", "got 'bogus'"), (True, "got True (bool)")]
    + ([] if torch.cuda.is_available() else [("cuda", "CUDA is not available")]),
)
def test_devices_are_checked(device, said):
    with pytest.raises(tms.InputError, match="device: expected") as info:
        tms.CorrectionGP(device=device)
    assert said in str(info.value)


def test_correction_error_needs_a_system(fitted):
    _, gp, _, _ = fitted
    with pytest.raises(tms.InputError, match="system: expected a torchmisspec.MisspecifiedSystem .* got NoneType"):
        tms.correction_error(gp, system=None)


# ------------------------------------------------------------------------------------ corrupt and unusual files
def test_an_empty_model_file_is_refused(tmp_path):
    (tmp_path / "m.pt").write_bytes(b"")
    with pytest.raises(
        tms.InputError, match=r"expected a CorrectionGP file written by CorrectionGP.save, got an empty"
    ):
        tms.CorrectionGP.load(tmp_path / "m.pt")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_npz_keeps_the_dtype(tmp_path, dtype):
    t = torch.linspace(0, 1, 5, dtype=DT)
    y = torch.randn(2, 5, 2, generator=torch.Generator().manual_seed(0), dtype=DT)
    data = tms.Trajectories(t.to(dtype), y.to(dtype))
    data.save(tmp_path / "d.npz")
    back = tms.Trajectories.load(tmp_path / "d.npz")
    assert back.dtype == dtype
    assert torch.equal(back.states, data.states) and torch.equal(back.times, data.times)


# ----------------------------------------------------------------------------------------------- silent inf
def test_rmse_of_huge_finite_errors_is_finite():
    big = torch.full((2, 3, 1), 1e200, dtype=DT)
    assert float(tms.trajectory_rmse(big, torch.zeros_like(big))) == pytest.approx(1e200, rel=1e-12)
    assert torch.allclose(tms.trajectory_rmse(big, torch.zeros_like(big), per_trajectory=True), big[:, 0, 0])
    with pytest.raises(tms.InputError, match="overflow float64"):
        tms.trajectory_rmse(torch.full((1, 1, 1), 1.5e308, dtype=DT), torch.full((1, 1, 1), -1.5e308, dtype=DT))


# --------------------------------------------------------------------------------------------- low precision
def test_half_precision_derivatives_are_refused_clearly():
    t = torch.linspace(0, 1, 9).half()
    with pytest.raises(tms.InputError, match=r"states: expected float32 or float64 values, got float16"):
        tms.smoothed_derivative(torch.ones(1, 9, 1).half(), t)


# ------------------------------------------------------------------------------------- the command line
def test_an_interrupted_write_leaves_the_old_file_or_none(tmp_path):
    from torchmisspec.cli._common import write_csv

    def rows():
        yield [1, 2]
        raise KeyboardInterrupt

    out = tmp_path / "table.csv"
    with pytest.raises(KeyboardInterrupt):
        write_csv(out, ["a", "b"], rows())
    assert not out.exists() and list(tmp_path.iterdir()) == []  # nothing half-written, no temporary left
    out.write_text("a,b\n0,0\n")
    with pytest.raises(KeyboardInterrupt):
        write_csv(out, ["a", "b"], rows())
    assert out.read_text() == "a,b\n0,0\n" and len(list(tmp_path.iterdir())) == 1
    write_csv(out, ["a", "b"], [[1, 2]])
    assert out.read_text().splitlines() == ["a,b", "1,2"]


def test_ctrl_c_in_a_command_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    from torchmisspec import cli
    from torchmisspec.cli import _predict

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(_predict, "_predict", interrupted)
    argv = ["predict", "--model", "m.pt", "--system", "paper_linear", "--initial", "x.csv", "--times", "0:1:2"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["torchmisspec predict: interrupted; nothing more was written"]


# ------------------------------------------------------------------------------------ wrong without a warning
def test_correction_samples_are_data_not_a_graph():
    """A known model with a trainable parameter (an nn.Parameter) must not leave its graph in the samples."""
    k = torch.nn.Parameter(torch.tensor(1.0, dtype=DT))
    system = tms.MisspecifiedSystem(lambda y: -k * y, 1, correction_inputs=[0], correction_outputs=[0])
    truth = tms.MisspecifiedSystem(
        lambda y: -y, 1, correction=lambda x: -0.5 * x**2, correction_inputs=[0], correction_outputs=[0]
    )
    t = torch.linspace(0, 1, 8, dtype=DT)
    data = tms.simulate(truth, torch.tensor([[1.0], [2.0], [0.5]], dtype=DT), t)
    samples = tms.correction_samples(data, system)
    assert not samples.targets.requires_grad and samples.targets.grad_fn is None
    exact = tms.correction_samples(data, tms.MisspecifiedSystem(lambda y: -y, 1))
    assert torch.equal(samples.targets, exact.targets)


def test_no_experiments_is_refused_when_built():
    t = torch.linspace(0, 1, 4, dtype=DT)
    with pytest.raises(tms.ShapeError, match=r"states: expected at least one experiment with at least one time, got"):
        tms.Trajectories(t, torch.zeros(0, 4, 2, dtype=DT))


X = torch.linspace(0, 1, 8, dtype=DT).unsqueeze(-1)


@pytest.mark.parametrize(
    ("call", "said"),
    [
        (lambda: tms.CorrectionGP(per_output="yes"), "per_output: expected True or False, got 'yes' (str)"),
        (
            lambda: tms.CorrectionGP(max_iter=5).fit(X, torch.sin(3 * X), progress=1),
            "progress: expected True or False, got 1 (int)",
        ),
    ],
)
def test_switches_are_booleans(call, said):
    """A truthy string or number was taken as a switch (relevance='no' turned relevance on)."""
    with pytest.raises(tms.InputError) as info:
        call()
    assert said in str(info.value)


def test_fit_switches_are_booleans(fitted):
    system, gp, _, times = fitted
    data = tms.simulate(system, tms.design.candidates.grid(system.domain, 2), times)
    with pytest.raises(tms.InputError, match=r"refine: expected True, False or None, got 'no' \(str\)"):
        tms.fit_correction(data, system, refine="no", progress=False)
    with pytest.raises(tms.InputError, match=r"relevance: expected True, False or None, got 'no' \(str\)"):
        tms.fit_trajectories(gp, system, data, relevance="no")
