"""Candidate generators (torchmisspec.design.candidates): grid, uniform_box, orbits."""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.design import candidates
from torchmisspec.systems import PAPER_GRAVITY_KNOWN_MASS, paper_gravity

BOX = ((-1.0, 1.0), (-2.0, 3.0))


# ------------------------------------------------------------------------------------------------------- grid
def test_grid_is_the_tensor_product_of_evenly_spaced_axes():
    points = candidates.grid(BOX, 5)
    assert points.shape == (25, 2) and points.dtype == torch.float64
    xs, ys = torch.linspace(-1, 1, 5, dtype=torch.float64), torch.linspace(-2, 3, 5, dtype=torch.float64)
    torch.testing.assert_close(points, torch.cartesian_prod(xs, ys))  # last coordinate fastest


def test_grid_paper_5_2_and_three_dimensions():
    paper = candidates.grid(tms.systems.paper_linear().domain, 13)  # 13 x 13 on [-1, 1]^2
    assert paper.shape == (169, 2) and torch.unique(paper[:, 0]).numel() == 13
    assert (paper.min(0).values == -1).all() and (paper.max(0).values == 1).all()
    cube = candidates.grid(((0, 1),) * 3, 3, dtype=torch.float32)
    assert cube.shape == (27, 3) and cube.dtype == torch.float32
    assert {tuple(p) for p in cube.tolist()} == {
        (a / 2, b / 2, c / 2) for a in range(3) for b in range(3) for c in range(3)
    }


@pytest.mark.parametrize(
    "domain, size, error, message",
    [
        (BOX, 1, tms.InputError, "size: expected an integer >= 2, got 1"),
        (BOX, 4.0, tms.InputError, r"size: expected an integer >= 2, got 4.0 \(float\)"),
        (((1, 0),), 3, tms.InputError, "domain: expected at least one interval with finite lo < hi"),
        ((1, 2), 3, tms.InputError, r"domain: expected a sequence of \(lo, hi\) pairs"),
    ],
)
def test_grid_rejects_bad_input(domain, size, error, message):
    with pytest.raises(error, match=message):
        candidates.grid(domain, size)


# ------------------------------------------------------------------------------------------------ uniform_box
def test_uniform_box_draws_inside_the_box_reproducibly():
    a = candidates.uniform_box(2000, BOX, generator=torch.Generator().manual_seed(0))
    b = candidates.uniform_box(2000, BOX, generator=torch.Generator().manual_seed(0))
    assert a.shape == (2000, 2) and a.dtype == torch.float64 and torch.equal(a, b)
    lo, hi = torch.tensor([-1.0, -2.0], dtype=torch.float64), torch.tensor([1.0, 3.0], dtype=torch.float64)
    assert ((a >= lo) & (a <= hi)).all()
    # uniform: mean (lo + hi) / 2 and std (hi - lo) / sqrt(12), to 5 standard errors of 2000 draws
    torch.testing.assert_close(a.mean(0), (lo + hi) / 2, atol=5 * float((hi - lo).max()) / math.sqrt(12 * 2000), rtol=0)
    torch.testing.assert_close(a.std(0), (hi - lo) / math.sqrt(12), rtol=0.05, atol=0)
    assert candidates.uniform_box(3, BOX, dtype=torch.float32).dtype == torch.float32


@pytest.mark.parametrize(
    "n, domain, message",
    [
        (0, BOX, "n: expected an integer >= 1, got 0"),
        (True, BOX, r"n: expected an integer >= 1, got True \(bool\)"),
        (3, ((0, float("inf")),), "domain: expected at least one interval with finite lo < hi"),
    ],
)
def test_uniform_box_rejects_bad_input(n, domain, message):
    with pytest.raises(tms.InputError, match=message):
        candidates.uniform_box(n, domain)


# ----------------------------------------------------------------------------------------------------- orbits
def test_orbits_are_circular_counter_clockwise_orbits_about_the_known_mass():
    y0 = candidates.orbits(200, generator=torch.Generator().manual_seed(0))
    assert y0.shape == (200, 4) and y0.dtype == torch.float64
    x, v = y0[:, :2], y0[:, 2:]
    r = torch.linalg.vector_norm(x, dim=-1)
    assert (x.abs() <= 2.0).all() and (r >= 0.75).all()  # in the square, outside the disc
    torch.testing.assert_close((x * v).sum(-1), torch.zeros(200, dtype=torch.float64), atol=1e-12, rtol=0)  # v ⟂ x
    torch.testing.assert_close(torch.linalg.vector_norm(v, dim=-1), torch.sqrt(PAPER_GRAVITY_KNOWN_MASS / r))
    assert (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0] > 0).all()  # counter-clockwise


def test_orbits_stay_circular_under_the_known_model():
    """The default mass is the one of paper_gravity's G: each orbit is what G predicts, a circle of its radius."""
    system = paper_gravity()
    y0 = candidates.orbits(5, generator=torch.Generator().manual_seed(1))
    states = tms.simulate(system, y0, torch.linspace(0, 3, 7, dtype=torch.float64), known_only=True).states
    radii = torch.linalg.vector_norm(states[..., :2], dim=-1)
    torch.testing.assert_close(radii, radii[:, :1].expand_as(radii), rtol=1e-6, atol=0)


def test_orbits_mass_and_geometry_arguments():
    y0 = candidates.orbits(50, mass=2.0, half_width=1.0, min_radius=0.5, generator=torch.Generator().manual_seed(2))
    r = torch.linalg.vector_norm(y0[:, :2], dim=-1)
    assert (y0[:, :2].abs() <= 1.0).all() and (r >= 0.5).all()
    torch.testing.assert_close(torch.linalg.vector_norm(y0[:, 2:], dim=-1), torch.sqrt(2.0 / r))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"n": 0}, "n: expected an integer >= 1, got 0"),
        ({"mass": 0.0}, "mass: expected a positive finite number, got 0.0"),
        ({"mass": "heavy"}, r"mass: expected a positive finite number, got 'heavy' \(str\)"),
        ({"min_radius": 2.0}, r"min_radius: expected 0 < min_radius < half_width=2.0, got 2.0"),
        ({"half_width": -1.0}, "half_width: expected a positive finite number, got -1.0"),
    ],
)
def test_orbits_reject_bad_input(kwargs, message):
    with pytest.raises(tms.InputError, match=message):
        candidates.orbits(**kwargs)


def test_the_known_mass_is_defined_once():
    assert paper_gravity().known.masses.tolist() == [PAPER_GRAVITY_KNOWN_MASS]
