"""Calibration from one experiment: its time cut in pieces, each forecast by the model refitted on the others
(issue 41: "with one experiment, calibration holds out later times instead of needing two experiments")."""

from __future__ import annotations

import pytest
import torch

import torchmisspec as tms
from torchmisspec.gp._calibration import BandCalibration
from torchmisspec.learning.choice._time_pieces import MIN_PIECE, piece_samples, time_pieces

DT = torch.float64


@pytest.fixture(scope="module")
def one():
    """paper 5.1's system, one experiment of 21 times (3 pieces of 7), oracle derivatives with a little noise."""
    system = tms.systems.paper_linear()
    traj = tms.simulate(system, torch.tensor([[0.8, -0.5]], dtype=DT), torch.linspace(0, 6, 21, dtype=DT))
    g = torch.Generator().manual_seed(1)
    samples = tms.correction_samples(traj, system, derivative="oracle", noise_std=1e-3, generator=g)
    return system, traj, samples


def test_each_sample_is_labelled_with_the_piece_of_its_time(one):
    _, traj, samples = one
    pieces = time_pieces(traj)
    labelled = piece_samples(samples, traj)
    # sample n is the n-th time: its piece is the one whose times contain it, and its state is that piece's
    starts = torch.tensor([0, *pieces.lengths]).cumsum(0)
    for k in range(pieces.num_experiments):
        rows = (labelled.experiment == k).nonzero().flatten()
        assert rows.tolist() == list(range(int(starts[k]), int(starts[k + 1])))
        torch.testing.assert_close(labelled.states[rows], pieces.experiments()[k][1])
    torch.testing.assert_close(labelled.targets, samples.targets)  # nothing else changes


def test_samples_of_other_data_are_refused(one):
    system, traj, samples = one
    with pytest.raises(tms.InputError, match=r"one sample per fully observed time .*\(21\), got 20"):
        piece_samples(samples.subset(torch.arange(20)), traj)
    two = tms.simulate(system, torch.tensor([[0.8, -0.5], [0.1, 0.2]], dtype=DT), torch.linspace(0, 6, 21, dtype=DT))
    with pytest.raises(tms.InputError, match="one fully measured experiment"):
        piece_samples(samples, two)


def test_one_experiment_is_calibrated_on_its_time_pieces(one):
    system, traj, samples = one
    model = tms.CorrectedODE(system, tms.CorrectionGP().fit(samples))
    cal = model.calibrate(traj, samples, num_samples=16, generator=torch.Generator().manual_seed(0), progress=False)
    assert cal.held_out == "time pieces" and cal.folds == time_pieces(traj).num_experiments
    # every held-out time after each piece's first, each component: the pieces' points, not the experiment's
    assert cal.num_points == 2 * (traj.lengths[0] - cal.folds)
    assert model.gp.calibration_ is cal and "folds of time pieces" in str(cal)
    # the same calibration by hand: the pieces as experiments, the samples relabelled
    by_hand = tms.prediction.calibration.calibrate_bands(
        model, time_pieces(traj), piece_samples(samples, traj), num_samples=16,
        generator=torch.Generator().manual_seed(0), progress=False,
    )  # fmt: skip
    assert by_hand.scale == cal.scale and by_hand.held_out == "experiments"


def test_one_experiment_too_short_or_partly_measured_is_refused_with_the_fix(one):
    system, traj, samples = one
    model = tms.CorrectedODE(system, tms.CorrectionGP().fit(samples))
    t, y = traj.experiments()[0]
    short = tms.Trajectories(t[: 2 * MIN_PIECE - 1], y[: 2 * MIN_PIECE - 1].unsqueeze(0))
    with pytest.raises(tms.InputError, match=rf"at least {2 * MIN_PIECE} times, got one of {2 * MIN_PIECE - 1} times"):
        model.calibrate(short, samples)
    partial = y.clone()
    partial[1:, 1] = float("nan")
    with pytest.raises(tms.InputError, match="some state not measured.*collect another experiment"):
        model.calibrate(tms.Trajectories(t, partial.unsqueeze(0)), samples)


def test_what_was_held_out_is_saved_and_a_damaged_record_refused(one, tmp_path):
    record = dict(
        scale=2.0, level=0.9, coverage_at_one=0.7, coverage=0.9, scales=[1.0, 2.0], coverages=[0.7, 0.9], folds=3,
        refit=True, num_points=36, held_out="time pieces",
    )  # fmt: skip
    assert BandCalibration.from_dict(record, "m.pt").held_out == "time pieces"
    old = {k: v for k, v in record.items() if k != "held_out"}  # a file written before the field: experiments
    assert BandCalibration.from_dict(old, "m.pt").held_out == "experiments"
    with pytest.raises(tms.InputError, match=r"m\.pt: expected the calibration's held-out data .*got 'days'"):
        BandCalibration.from_dict({**record, "held_out": "days"}, "m.pt")


class _FailsFromLargeStates(tms.CorrectedODE):
    """A model whose posterior cannot be integrated from a state with a first component above 0.5."""

    def posterior(self, y0, *args, **kwargs):
        if bool((torch.as_tensor(y0)[..., 0] > 0.5).any()):
            raise tms.IntegrationError("stalled (test)")
        return super().posterior(y0, *args, **kwargs)


def test_a_fold_whose_held_out_paths_fail_is_left_out_and_said(one):
    system = tms.systems.paper_linear()
    y0 = torch.tensor([[0.8, -0.5], [0.1, 0.2], [-0.3, 0.4]], dtype=DT)
    traj = tms.simulate(system, y0, torch.linspace(0, 3, 9, dtype=DT))
    samples = tms.correction_samples(traj, system, derivative="oracle")
    model = _FailsFromLargeStates(system, tms.CorrectionGP().fit(samples))
    with pytest.warns(tms.TorchMisspecWarning, match=r"paths of 1 of 3 folds cannot be integrated .*stalled \(test\)"):
        cal = model.calibrate(traj, samples, folds=3, num_samples=8, progress=False)
    assert cal.num_points == 2 * 2 * 8  # the two experiments that remain, 8 times after the first, 2 components
    with pytest.raises(tms.FittingError, match="stalled"):  # none remains
        model.calibrate(tms.simulate(system, y0[:1].expand(2, 2), torch.linspace(0, 3, 9, dtype=DT)), folds=2,
                        samples=tms.correction_samples(tms.simulate(system, y0[:1].expand(2, 2),
                        torch.linspace(0, 3, 9, dtype=DT)), system, derivative="oracle"), progress=False)  # fmt: skip


@pytest.mark.slow
def test_the_command_line_calibrates_one_experiment_on_its_time_pieces(tmp_path, capsys, one):
    """A lab's CSV of one experiment: 'torchmisspec calibrate' holds out pieces of its time (it said it needs two
    experiments), and a file of one partly measured experiment is refused in one line with the fix."""
    from torchmisspec.cli import main

    _, traj, _ = one
    t, y = traj.experiments()[0]
    y = y + 0.01 * torch.randn(y.shape, generator=torch.Generator().manual_seed(2), dtype=DT)  # as measured
    rows = [f"{a:.6f},{b[0]:.8f},{b[1]:.8f}" for a, b in zip(t.tolist(), y.tolist(), strict=True)]
    (tmp_path / "run.csv").write_text("time,u,v\n" + "\n".join(rows) + "\n")
    (tmp_path / "lin.py").write_text(
        "import torch\nfrom torchmisspec import MisspecifiedSystem\n\n\ndef known(y):\n"
        "    return torch.stack([-0.1 * y[..., 0] - y[..., 1], y[..., 0] - 0.1 * y[..., 1]], dim=-1)\n\n\n"
        "system = MisspecifiedSystem(known, 2, state_names=['u', 'v'], name='linear')\n"
    )
    lab = ["--data", str(tmp_path / "run.csv"), "--system", f"{tmp_path / 'lin.py'}:system", "--quiet"]
    assert main(["fit", *lab, "--no-calibrate", "--out", str(tmp_path / "m.pt")]) == 0
    capsys.readouterr()
    assert main(["calibrate", *lab, "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "c.pt")]) == 0
    assert "folds of time pieces" in capsys.readouterr().out
    assert tms.CorrectionGP.load(tmp_path / "c.pt").calibration_.held_out == "time pieces"
    gappy = rows[:1] + [r.rsplit(",", 1)[0] + "," for r in rows[1:]]  # v measured only at the start
    (tmp_path / "gappy.csv").write_text("time,u,v\n" + "\n".join(gappy) + "\n")
    lab[1] = str(tmp_path / "gappy.csv")
    assert main(["calibrate", *lab, "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "g.pt")]) == 2
    [error] = [x for x in capsys.readouterr().err.splitlines() if "error:" in x]  # one line: the refusal
    assert error.startswith("torchmisspec calibrate: error: trajectories:") and "some state not measured" in error
