"""Measured combinations of states (issue 24 part 3: an observation matrix H): the readout, its data, the fit.

The system is a ligand-binding model the package does not ship: free ligand binds reversibly (the lab's model),
and the bound ligand is also internalised by a saturable pathway (the missing term). The lab counts the total
radioactivity, free + bound, and knows only each run's dose (free at the start); neither state is measured alone.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.cli import main
from torchmisspec.learning.refinement import partial
from torchmisspec.learning.refinement.trajectory_fit import _shooting

DT = torch.float64

BINDING_SYSTEM = """
import torch
import torchmisspec as tms


def rates(y):
    free, bound = y[..., 0], y[..., 1]
    return torch.stack([-1.0 * free + 0.3 * bound, 1.0 * free - 0.3 * bound], dim=-1)


def binding():
    return tms.MisspecifiedSystem(
        rates, 2, state_names=["free", "bound"], correction_inputs=["bound"], correction_outputs=["bound"],
        name="binding",
    )
"""


def rates(y):
    free, bound = y[..., 0], y[..., 1]
    return torch.stack([-1.0 * free + 0.3 * bound, 1.0 * free - 0.3 * bound], dim=-1)


def internalised(x):
    return (-0.6 * x[..., 0] / (0.4 + x[..., 0])).unsqueeze(-1)


def truth():
    return tms.MisspecifiedSystem(rates, 2, correction=internalised, correction_inputs=[1], correction_outputs=[1])


def lab_model():
    return tms.MisspecifiedSystem(
        rates, 2, state_names=["free", "bound"], correction_inputs=["bound"], correction_outputs=["bound"]
    )


TOTAL = tms.Readout.parse(["total = free + bound"], ["free", "bound"])


def lab_data(g, K=8):
    """Ragged irregular counts of the total with 2 % noise; free known at the start (the dose), bound not given."""
    doses = 0.5 + 2.5 * torch.rand(K, generator=g, dtype=DT)
    times, states, readings = [], [], []
    for k in range(K):
        n = int(torch.randint(12, 20, (1,), generator=g))
        t = torch.sort(torch.rand(n, generator=g, dtype=DT) * 8).values
        t[0] = 0.0
        y = tms.simulate(truth(), torch.stack([doses[k], torch.zeros((), dtype=DT)]).unsqueeze(0), t).states[0]
        observed = torch.full_like(y, math.nan)
        observed[0, 0] = doses[k]
        times.append(t)
        states.append(observed)
        readings.append(TOTAL(y) * (1 + 0.02 * torch.randn(n, 1, generator=g, dtype=DT)))
    return tms.Trajectories(times, states, state_names=("free", "bound"), readout=TOTAL, readings=readings)


def test_readout_parse_weights_and_errors():
    r = tms.Readout.parse(["a280 = 1.5*free + bound - 0.5 free", "tracer = 2e-1 bound"], ["free", "bound"])
    assert torch.equal(r.matrix, torch.tensor([[1.0, 1.0], [0.0, 0.2]], dtype=torch.float64))
    assert r.names == ("a280", "tracer") and r.describe() == ["a280 = free + bound", "tracer = 0.2*bound"]
    assert tms.Readout.from_weights({"a280": {"free": 1.0, "bound": 1.0}}, ["free", "bound"]) == TOTAL.__class__(
        [[1.0, 1.0]], ["a280"]
    )
    y = torch.tensor([[2.0, 3.0]], dtype=DT)
    assert torch.allclose(r(y), torch.tensor([[5.0, 0.6]], dtype=DT), rtol=0, atol=1e-15)
    for text, said in [
        ("total free + bound", "expected 'name = weight*state"),
        ("total = free + cell", "expected states among ['free', 'bound'], got 'cell'"),
        ("total = free bound", "joined by + or -"),
        ("total = free - free", "nonzero weight in every row"),
    ]:
        with pytest.raises(tms.InputError, match=r".*") as info:
            tms.Readout.parse([text], ["free", "bound"])
        assert said in str(info.value), (text, str(info.value))
    with pytest.raises(tms.InputError, match="finite number, got True"):
        tms.Readout.from_weights({"t": {"free": True}}, ["free", "bound"])
    with pytest.raises(tms.InputError, match="named apart from the states"):
        tms.Readout([[1.0, 1.0]], ["free"], state_names=["free", "bound"])


def test_trajectories_keep_readings(tmp_path):
    data = lab_data(torch.Generator().manual_seed(1), K=3)
    assert data.readout == TOTAL and data.is_ragged and not data.measured.any()
    assert "readings total = free + bound" in repr(data)
    values, mask = data.observed_values()
    assert values.shape == (3, max(data.lengths), 3)
    # rows with only a reading are kept; indexing, to(), filled() and the files keep the readings
    assert data.lengths == tuple(len(r) for r in data.readings)
    sub = data[[2, 0]]
    assert torch.equal(sub.readings[0], data.readings[2]) and sub.readout == TOTAL
    assert data.to(torch.float32).readings[1].dtype == torch.float32
    assert torch.equal(data.filled().readings[1], data.readings[1])
    for name in ["lab.csv", "lab.npz"]:
        data.save(tmp_path / name)
        back = tms.Trajectories.load(tmp_path / name, readout=TOTAL if name.endswith(".csv") else None)
        assert back.readout == TOTAL
        assert all(torch.equal(a, b) for a, b in zip(back.readings, data.readings, strict=True))
    # a lab's table without a column for bound: read only through the total
    lines = (tmp_path / "lab.csv").read_text().splitlines()
    (tmp_path / "counts.csv").write_text(
        "\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != 3) for line in lines) + "\n"
    )
    back = tms.Trajectories.load(tmp_path / "counts.csv", readout=TOTAL)
    assert back.state_names == ("free", "bound") and bool(torch.isnan(torch.cat(back.states)[:, 1]).all())
    with pytest.raises(tms.InputError, match="expected the values of the readout"):
        tms.Trajectories(data.times, list(data.states), readout=TOTAL)
    with pytest.raises(tms.InputError, match="expected a readout saying what they measure"):
        tms.Trajectories(list(data.times), list(data.states), readings=list(data.readings))
    with pytest.raises(tms.ShapeError, match="readings"):
        tms.Trajectories(list(data.times), list(data.states), readout=TOTAL, readings=list(data.readings)[:2])


def test_residuals_read_the_path_through_the_readout():
    """The fit's residuals are H y(t) - z on the readings (and y - y_obs on the states), against a direct solve."""
    g = torch.Generator().manual_seed(2)
    data = lab_data(g, K=3)
    y0 = torch.tensor([[2.0, 0.1], [1.0, 0.0], [0.7, 0.3]], dtype=DT)
    data = data.with_initial_states(y0)
    solver = dict(rtol=1e-10, atol=1e-12, max_steps=None, what="test")
    residuals, n_obs, _ = _shooting(data, "single", solver, lab_model())
    got = residuals(lambda y, t=None, u=None: rates(y), None, None)
    expected = []
    for k, (t, _) in enumerate(data.experiments()):
        path = tms.simulate(lab_model(), y0[k : k + 1], t, known_only=True, rtol=1e-10, atol=1e-12).states[0]
        z = data.readings[k]
        states = data.states[k]
        seen_y, seen_z = torch.isfinite(states), torch.isfinite(z)
        r = torch.cat(
            [torch.where(seen_y, path - states, 0.0), torch.where(seen_z, path @ TOTAL.matrix.T - z, 0.0)], -1
        )
        expected.append(r)
    assert torch.allclose(got, torch.cat(expected), atol=1e-7)
    assert n_obs == sum(
        int(torch.isfinite(z).sum()) + int(torch.isfinite(y).sum())
        for y, z in zip(data.states, data.readings, strict=True)
    )


def test_fit_through_the_readout_predicts_both_states():
    """Neither state measured alone: F on bound is seen through the total, learned through the ODE, predicts well."""
    g = torch.Generator().manual_seed(3)
    data = lab_data(g)
    system = lab_model()
    report = partial.identifiability(system, data)
    assert report.seen_by == (("total",),) and report.from_paths
    gp = tms.fit_correction(data, system, progress=False)
    assert "seen through total" in gp.identifiability_.summary()
    model = tms.CorrectedODE(system, gp)
    y0 = torch.tensor([[1.0, 0.0], [2.5, 0.0], [3.5, 0.0]], dtype=DT)  # 3.5: beyond the doses given
    t = torch.linspace(0, 8, 30, dtype=DT)
    reference = tms.simulate(truth(), y0, t).states
    known = tms.simulate(system, y0, t, known_only=True).states
    ratio = float(tms.trajectory_rmse(model.predict(y0, t), reference)) / float(tms.trajectory_rmse(known, reference))
    assert ratio <= 0.05, ratio
    # the band of what the instrument reads: the draws read out (free + bound), quantiles of their sums
    post = model.posterior(y0, t, num_samples=16, generator=torch.Generator().manual_seed(0), scale=1.0)
    read = post.read(TOTAL)
    assert read.state_names == ("total",)
    assert torch.allclose(read.samples, post.samples.sum(-1, keepdim=True))
    assert torch.allclose(read.mean_path, post.mean_path.sum(-1, keepdim=True))
    lower, upper = read.interval(0.8)
    assert bool((lower <= read.mean_path + 1e-9).all() and (read.mean_path <= upper + 1e-9).all())
    # the readings alone give the bound state's start: 0 up to the noise
    assert torch.allclose(gp.initial_states_[:, 1], torch.zeros(8, dtype=DT), atol=0.1)
    # without the readout nothing is measured: refused, naming what is missing
    with pytest.raises(tms.InputError):
        tms.fit_correction(data.with_readout(None), system, progress=False)


def test_cli_reads_the_readout_column(tmp_path, capsys):
    data = lab_data(torch.Generator().manual_seed(4), K=4)
    (tmp_path / "binding.py").write_text(BINDING_SYSTEM)
    lines = ["run,minutes,free,radioactivity"]
    for k, (t, y) in enumerate(data.experiments()):
        for i in range(len(t)):
            free = "" if math.isnan(float(y[i, 0])) else f"{float(y[i, 0]):.6g}"
            lines.append(f"r{k},{float(t[i]):.6g},{free},{float(data.readings[k][i, 0]):.6g}")
    (tmp_path / "lab.csv").write_text("\n".join(lines) + "\n")
    common = [
        "--system",
        f"{tmp_path / 'binding.py'}:binding",
        "--time-column",
        "minutes",
        "--experiment-column",
        "run",
    ]
    readout = ["--readout", "radioactivity = free + bound"]
    model = tmp_path / "m.pt"
    args = ["fit", "--data", str(tmp_path / "lab.csv"), *common, *readout, "--out", str(model), "--quiet"]
    assert main(args) == 0
    said = capsys.readouterr().out
    assert "seen through radioactivity" in said and "measured states and readings" in said
    assert "calibrated bands" in said  # on the held-out readings
    (tmp_path / "doses.csv").write_text("run,free,bound\nlow,1.0,0\nhigh,2.5,0\n")
    out = tmp_path / "predicted.csv"
    predict = ["predict", "--model", str(model), "--initial", str(tmp_path / "doses.csv"), "--times", "0:8:9"]
    assert main([*predict, *common, *readout, "--out", str(out), "--quiet"]) == 0
    header, *rows = (line.split(",") for line in out.read_text().splitlines())
    assert header[:3] == ["run", "minutes", "free_mean"] and header[-3:] == [
        f"radioactivity_{s}" for s in ("mean", "lower", "upper")
    ]
    for row in rows:  # the reading's mean path is the sum of the states' mean paths
        free, bound, total = (float(row[header.index(f"{n}_mean")]) for n in ("free", "bound", "radioactivity"))
        assert abs(free + bound - total) < 1e-9
    # design reads no table with --model: a --readout there would be ignored, so it is refused
    design = ["design", "--model", str(model), "--candidates", str(tmp_path / "doses.csv"), "--times", "0:8:5"]
    assert main([*design, "--budget", "1", *common, *readout, "--out", str(tmp_path / "p.csv"), "--quiet"]) == 2
    assert "--readout: expected --data" in capsys.readouterr().err
    # a readout naming a state the system does not have: one line, exit 2
    bad = ["--readout", "radioactivity = free + bund"]
    assert main(["fit", "--data", str(tmp_path / "lab.csv"), *common, *bad, "--out", str(tmp_path / "x.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "got 'bund'" in err[0]
