"""The learning pipeline as stage objects (issue 42, item 1): ``Pipeline`` runs what ``fit_correction`` runs, its
stages check their options where they are made, the keywords and the stages describe one another, and a fit records
the pipeline it came from (what a campaign refits with)."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchmisspec as tms
from torchmisspec import design
from torchmisspec.learning import Candidates, Evidence, HeldOut, Pipeline, Refinement, Samples

DT = torch.float64
TIMES = torch.linspace(0, 6, 21, dtype=DT)


@pytest.fixture(scope="module")
def lab():
    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(3)
    y0 = design.candidates.uniform_box(5, system.domain, generator=g)
    states = tms.simulate(system, y0, TIMES).states
    noisy = states * (1 + 0.005 * torch.randn(states.shape, generator=g, dtype=DT))
    return system, tms.Trajectories(TIMES, noisy, state_names=("a", "b"))


def _quiet(fit, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tms.TorchMisspecWarning)
        return fit(*args, **kwargs)


def test_the_pipeline_names_its_stages_in_the_order_the_data_pass():
    assert Pipeline.stages[:4] == ("samples", "candidates", "choice", "refinement")
    assert Pipeline.stages[-1] == "calibration"
    assert tms.Pipeline is Pipeline


@pytest.mark.parametrize("select", ["cv", "evidence"])
def test_a_pipeline_fits_what_fit_correction_fits_with_the_same_options(lab, select):
    system, data = lab
    keywords = dict(select=select, derivative="central", folds=3)
    direct = _quiet(tms.fit_correction, data, system, progress=False, **keywords)
    pipeline = Pipeline(
        samples=Samples(derivative="central"), choice=HeldOut(folds=3) if select == "cv" else Evidence()
    )
    staged = _quiet(pipeline.fit, data, system, progress=False)
    assert staged.kernel == direct.kernel and staged.derivative_ == direct.derivative_
    torch.testing.assert_close(staged.train_inputs_, direct.train_inputs_)
    torch.testing.assert_close(staged.posterior().mean(data.flat_states()[:, :2]),
                               direct.posterior().mean(data.flat_states()[:, :2]))  # fmt: skip
    assert staged.pipeline_.choice == pipeline.choice and staged.pipeline_.noise.name == direct.noise_.name
    assert direct.pipeline_.keywords()["select"] == select and direct.pipeline_.samples.derivative == "central"


def test_keywords_and_stages_describe_each_other():
    template = tms.CorrectionGP(lengthscale=0.5)
    keywords = dict(gp=template, candidates=None, select="evidence", derivative="gp", folds=5, refine=False)
    pipeline = Pipeline.from_keywords(**keywords, noise="relative", order=4)
    assert pipeline.candidates.gp is template and isinstance(pipeline.choice, Evidence)
    assert pipeline.refinement == Refinement(through_ode=False) and pipeline.samples.order == 4
    assert pipeline.keywords() == {**keywords, "noise": "relative", "order": 4}
    assert Pipeline.from_keywords(**pipeline.keywords()) == pipeline
    assert Pipeline().keywords() == Pipeline.from_keywords().keywords()


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: HeldOut(folds=1), "folds: expected an integer >= 2, got 1"),
        (lambda: Samples(derivative=2), r"derivative: expected the name of an estimator .*got 2 \(int\)"),
        (lambda: Samples(window=0), "window: expected an integer >= 1, got 0"),
        (lambda: Refinement(through_ode="yes"), r"through_ode: expected True, False or None, got 'yes'"),
        (lambda: Candidates(gp="rbf"), "gp: expected a CorrectionGP template or None, got str"),
        (lambda: Candidates(models=[]), "candidates: expected a non-empty list of CorrectionGP templates"),
        (lambda: Pipeline(choice="cv"), r"choice: expected HeldOut\(folds=...\) or Evidence\(\)"),
        (lambda: Pipeline(samples="central"), r"samples: expected a Samples .*got str"),
        (lambda: Pipeline.from_keywords(select="aic"), "select: expected 'cv' .* or 'evidence' .*got 'aic'"),
        (lambda: Pipeline.from_keywords(windw=5), r"unexpected option\(s\) \['windw'\]"),
    ],
)
def test_each_stage_refuses_a_bad_option_where_it_is_made(make, message):
    with pytest.raises(tms.InputError, match=message):
        make()


def test_a_pipeline_and_the_options_it_holds_are_not_given_together(lab):
    system, data = lab
    with pytest.raises(tms.InputError, match=r"either a pipeline or the options it holds, got both .*\['folds'\]"):
        tms.fit_correction(data, system, pipeline=Pipeline(), folds=3)
    with pytest.raises(tms.InputError, match="pipeline: expected a torchmisspec.Pipeline or None, got dict"):
        tms.fit_correction(data, system, pipeline={"folds": 3})


def test_the_samples_stage_gives_the_samples_of_correction_samples(lab):
    system, data = lab
    staged = Samples(derivative="smooth", window=5)(data, system)
    direct = tms.correction_samples(data, system, derivative="smooth", window=5)
    torch.testing.assert_close(staged.targets, direct.targets)
    assert Samples(derivative="smooth", window=5).estimator == {"window": 5}
