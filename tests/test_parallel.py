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


@pytest.mark.slow
def test_a_study_in_a_process_pool_gives_the_serial_numbers():
    cfg = {**study_sampling_times.SMOKE, "realizations": 2}
    quiet = lambda *a, **k: None  # noqa: E731
    serial = study_sampling_times.study(cfg, log=quiet)
    with process_pool(2) as pool:
        pooled = study_sampling_times.study(cfg, log=quiet, executor=pool)
    assert pooled["runs"] == serial["runs"]


@pytest.mark.slow
def test_a_study_on_a_local_dask_cluster_gives_the_serial_numbers():
    distributed = pytest.importorskip("distributed")
    cfg = {**study_sampling_times.SMOKE, "realizations": 2}
    quiet = lambda *a, **k: None  # noqa: E731
    serial = study_sampling_times.study(cfg, log=quiet)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            pooled = study_sampling_times.study(cfg, log=quiet, executor=client.get_executor())
    assert pooled["runs"] == serial["runs"]
