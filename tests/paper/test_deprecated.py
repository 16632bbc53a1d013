"""The names that moved to torchmisspec.paper and torchmisspec.design.candidates still work, and warn."""

import importlib
import sys

import pytest
import torch

import torchmisspec as tms
from torchmisspec.design import candidates
from torchmisspec.paper import demo, figures, studies

BOX = ((-1.0, 1.0), (-2.0, 2.0))


def forget(name: str) -> None:
    """Make ``torchmisspec.<x>`` look never imported (no module in sys.modules, no attribute on the package)."""
    sys.modules.pop(name, None)
    vars(tms).pop(name.rpartition(".")[2], None)


@pytest.fixture(autouse=True)
def deprecated_modules_forgotten():
    """Each test imports the deprecated modules afresh (they warn once per import) and leaves them unimported."""
    names = ("torchmisspec.studies", "torchmisspec.reproduce", "torchmisspec.experiments")
    for name in names:
        forget(name)
    yield
    for name in names:
        forget(name)


def import_fresh(name: str):
    """Import ``name``, expecting its DeprecationWarning."""
    with pytest.warns(DeprecationWarning, match=rf"{name} is deprecated: use torchmisspec\.paper\."):
        return importlib.import_module(name)


def test_studies_module_warns_and_reexports():
    old = import_fresh("torchmisspec.studies")
    assert (old.StudyResult, old.linear_study, old.gravity_study) == (
        studies.StudyResult,
        studies.linear_study,
        studies.gravity_study,
    )
    torch.testing.assert_close(old.grid_candidates(BOX), candidates.grid(BOX, 13))  # the old default size
    torch.testing.assert_close(old.grid_candidates(BOX, 5), candidates.grid(BOX, 5))


def test_reproduce_module_warns_and_reexports():
    old = import_fresh("torchmisspec.reproduce")
    for name in old.__all__:
        assert getattr(old, name) is getattr(figures, name), name


def test_experiments_module_warns_and_reexports():
    old = import_fresh("torchmisspec.experiments")
    assert (old.DemoResult, old.linear_demo) == (demo.DemoResult, demo.linear_demo)
    assert old.uniform_in_box is candidates.uniform_box
    torch.testing.assert_close(
        old.uniform_in_box(4, BOX, generator=torch.Generator().manual_seed(1)),
        candidates.uniform_box(4, BOX, generator=torch.Generator().manual_seed(1)),
    )


def test_gravity_candidates_warns_and_draws_the_same_orbits():
    with pytest.warns(DeprecationWarning, match=r"gravity_candidates is deprecated; use .*candidates\.orbits"):
        old = tms.systems.gravity_candidates(25, generator=torch.Generator().manual_seed(4), min_radius=0.5)
    torch.testing.assert_close(old, candidates.orbits(25, generator=torch.Generator().manual_seed(4), min_radius=0.5))


def test_top_level_studies_attribute_warns():
    with pytest.warns(DeprecationWarning, match=r"torchmisspec\.studies is deprecated"):
        old = tms.studies
    assert old.linear_study is studies.linear_study
    assert "studies" not in tms.__all__ and "paper" not in tms.__all__
