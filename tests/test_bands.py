"""The band of S sampled paths covers ``level`` of new draws (order statistics of exchangeable draws)."""

import math

import pytest
import torch

import torchmisspec as tms
from torchmisspec.prediction._bands import band_quantiles, path_quantiles


@pytest.mark.parametrize("S, level", [(39, 0.9), (64, 0.9), (64, 0.5), (99, 0.95)])
def test_band_covers_a_new_draw_with_the_level(S, level):
    """Monte Carlo over 40,000 independent sets of S + 1 standard normal draws: the band of the first S covers the
    last with probability ``level`` (the plain quantiles, the old band, cover (S - 1)/(S + 1) level + ... less)."""
    gen = torch.Generator().manual_seed(0)
    reps = 40_000
    x = torch.randn(S + 1, reps, generator=gen, dtype=torch.float64)
    draws, new = x[:S], x[S]
    lo, hi = path_quantiles(draws, band_quantiles(level, S))
    hit = ((new >= lo) & (new <= hi)).double().mean()
    se = math.sqrt(level * (1 - level) / reps)
    assert abs(float(hit) - level) < 4 * se + 0.004  # 0.004: the interpolation between two neighbouring draws
    plain = torch.quantile(draws, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=torch.float64), dim=0)
    old = float(((new >= plain[0]) & (new <= plain[1])).double().mean())
    assert old < level - 4 * se  # the plain quantiles' band is too narrow: the bug this guards


def test_whole_ranks_are_exact():
    """S = 39, level 0.9: the band is the 2nd to the 38th smallest draw, which covers exactly 36/40 = 0.9."""
    qs = band_quantiles(0.9, 39)
    ranks = 1 + qs * 38
    torch.testing.assert_close(ranks, torch.tensor([2.0, 38.0], dtype=torch.float64))


def test_too_few_draws_warn_with_the_number_needed():
    with pytest.warns(tms.TorchMisspecWarning, match=r"num_samples=19\)"):
        qs = band_quantiles(0.9, 18)
    assert qs.tolist() == [0.0, 1.0]  # the draws' range
    with pytest.warns(tms.TorchMisspecWarning, match="no finite number"):
        band_quantiles(1.0, 100)


def test_enough_draws_do_not_warn(recwarn):
    band_quantiles(0.9, 19)
    band_quantiles(0.95, 39)
    assert not [w for w in recwarn if issubclass(w.category, tms.TorchMisspecWarning)]
