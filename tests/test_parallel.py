"""Independent tasks through an executor (torchmisspec.parallel): the same numbers as the serial run, in order."""

from __future__ import annotations

import concurrent.futures

import pytest

import torchmisspec as tms
from torchmisspec.paper import study_sampling_times
from torchmisspec.parallel import map_tasks, process_pool


def _square(x: int) -> int:
    return x * x


def test_map_tasks_keeps_the_order_with_any_executor():
    with concurrent.futures.ThreadPoolExecutor(3) as pool:
        assert map_tasks(_square, range(20), pool) == [x * x for x in range(20)]
    assert map_tasks(_square, range(5)) == [0, 1, 4, 9, 16]
    with pytest.raises(tms.InputError, match="executor: expected a concurrent.futures.Executor .* got int"):
        map_tasks(_square, range(3), 2)
    with pytest.raises(tms.InputError, match="workers: expected an integer >= 1, got 0"):
        process_pool(0)


STUDY_CFG = {**study_sampling_times.SMOKE, "realizations": 2}


def _quiet(*args, **kwargs) -> None:
    pass


@pytest.fixture(scope="module")
def serial_study():
    """The sampling-times study's smoke run, serial: the reference both executors' runs are compared to (run once
    for the module, not once per executor)."""
    return study_sampling_times.study(STUDY_CFG, log=_quiet)


@pytest.mark.slow
def test_a_study_in_a_process_pool_gives_the_serial_numbers(serial_study):
    with process_pool(2) as pool:
        pooled = study_sampling_times.study(STUDY_CFG, log=_quiet, executor=pool)
    assert pooled["runs"] == serial_study["runs"]


@pytest.mark.slow
def test_a_study_on_a_local_dask_cluster_gives_the_serial_numbers(serial_study):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            pooled = study_sampling_times.study(STUDY_CFG, log=_quiet, executor=client.get_executor())
    assert pooled["runs"] == serial_study["runs"]


def _calibration_case():
    import torch

    system = tms.systems.paper_linear()
    g = torch.Generator().manual_seed(5)
    times = torch.linspace(0.0, 6.0, 11, dtype=torch.float64)
    y0 = tms.design.candidates.uniform_box(6, system.domain, generator=g)
    clean = tms.simulate(system, y0, times)
    data = tms.Trajectories(times, clean.states * (1 + 0.003 * torch.randn(clean.states.shape, generator=g)))
    samples = tms.correction_samples(data, system)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-4).fit(samples)
    return tms.CorrectedODE(system, gp), data, samples


def test_calibration_folds_through_an_executor_give_the_serial_result():
    model, data, samples = _calibration_case()
    options = dict(folds=3, num_samples=20, refit=False, progress=False)
    serial = tms.calibrate_bands(model, data, samples, **options)
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        assert tms.calibrate_bands(model, data, samples, executor=pool, **options) == serial
    with pytest.raises(tms.InputError, match="executor: expected a concurrent.futures.Executor"):
        tms.calibrate_bands(model, data, samples, executor="pool", **options)


@pytest.mark.slow
def test_calibration_folds_in_a_process_pool_give_the_serial_result():
    model, data, samples = _calibration_case()
    options = dict(folds=3, num_samples=20, progress=False)  # refitted in each fold
    serial = tms.calibrate_bands(model, data, samples, **options)
    with process_pool(2) as pool:
        assert tms.calibrate_bands(model, data, samples, executor=pool, **options) == serial


def _nonlinear_design_case():
    import torch

    from torchmisspec.benchmarks.default_fit import predator_prey  # a nonlinear G, module-level (picklable)

    system = predator_prey()
    candidates = tms.design.candidates.uniform_box(30, system.domain, generator=torch.Generator().manual_seed(2))
    times = torch.linspace(0.0, 4.0, 6, dtype=torch.float64)
    gp = tms.CorrectionGP(lengthscale=1.0, outputscale=1e-2, noise_variance=1e-4)
    return system, candidates, times, gp


def test_design_proxies_in_chunks_through_an_executor_give_the_serial_design(monkeypatch):
    """The proxies of a nonlinear G are solved in chunks of PROXY_CHUNK candidates, one after another or through an
    executor: the same proxies and the same design; each chunk matches the one-batch solve to the solver's tolerance."""
    import torch

    from torchmisspec.design import _proxy

    system, candidates, times, gp = _nonlinear_design_case()
    whole = _proxy.proxy_paths("known", system, gp, candidates, times)
    monkeypatch.setattr(_proxy, "PROXY_CHUNK", 7)
    chunked = _proxy.proxy_paths("known", system, gp, candidates, times)
    torch.testing.assert_close(chunked, whole, rtol=1e-8, atol=1e-10)
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        assert torch.equal(_proxy.proxy_paths("known", system, gp, candidates, times, executor=pool), chunked)
        serial = tms.design.greedy(candidates, 4, system=system, times=times, gp=gp)
        pooled = tms.design.greedy(candidates, 4, system=system, times=times, gp=gp, executor=pool)
        campaign = tms.design.Campaign(system, candidates, times, gp, executor=pool)
        assert campaign.ask(4).tolist() == candidates[serial.indices].tolist()
    assert pooled.indices.tolist() == serial.indices.tolist() and pooled.information_gain == serial.information_gain
    with pytest.raises(tms.InputError, match="executor: expected a concurrent.futures.Executor"):
        tms.design.greedy(candidates, 2, system=system, times=times, gp=gp, executor=4)
    with pytest.raises(tms.InputError, match="executor: expected a concurrent.futures.Executor .* got str"):
        tms.design.Campaign(system, candidates, times, gp, executor="pool")


@pytest.mark.slow
def test_design_proxies_in_a_process_pool_give_the_serial_design(monkeypatch):
    from torchmisspec.design import _proxy

    system, candidates, times, gp = _nonlinear_design_case()
    monkeypatch.setattr(_proxy, "PROXY_CHUNK", 10)  # the workers import their own (4096): the chunks are made here
    serial = tms.design.greedy(candidates, 4, system=system, times=times, gp=gp)
    with process_pool(2) as pool:
        pooled = tms.design.greedy(candidates, 4, system=system, times=times, gp=gp, executor=pool)
    assert pooled.indices.tolist() == serial.indices.tolist() and pooled.information_gain == serial.information_gain
