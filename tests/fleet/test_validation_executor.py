"""The validation study's Monte Carlo through an executor gives the serial loop's results.

Issue 21 item 3: ``benchmarks/validate.py --scheduler tcp://HOST:PORT`` runs the seeds on a Dask
cluster; here a LocalCluster started by the test stands for it, reached by its address.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest

from drivegain.errors import InputError
from drivegain.identify.blas import limited_blas_threads
from drivegain.validation import estimators
from drivegain.validation.cluster import run_monte_carlo
from drivegain.validation.scenarios import SCENARIOS
from drivegain.validation.world import make_world


def _scenario(key: str) -> SimpleNamespace:
    return SimpleNamespace(key=key, seeds=lambda n: n)


def test_monte_carlo_on_an_executor_matches_the_serial_loop(monkeypatch) -> None:
    def fake_seed(world, seed, scenario):
        return (world, seed, scenario.key)

    monkeypatch.setattr(estimators, "run_seed", fake_seed)
    scenarios = [_scenario("equal"), _scenario("unequal")]
    far = time.perf_counter() + 600
    serial = estimators.monte_carlo("w", 5, far, scenarios, progress=lambda s: None)
    with ThreadPoolExecutor(2) as pool:
        mapped = estimators.monte_carlo(
            "w", 5, far, scenarios, progress=lambda s: None, executor=pool
        )
        assert mapped == serial
        cut = estimators.monte_carlo("w", 5, 0.0, scenarios, lambda s: None, executor=pool)
    assert {k: len(v) for k, v in cut.items()} == {"equal": 1, "unequal": 1}
    assert serial["equal"][3] == ("w", 3, "equal")


def _numbers(results: dict[str, list[estimators.SeedResult]]) -> dict[str, np.ndarray]:
    """Every estimate of every seed, method and payload fit, flattened by name."""
    out = {}
    for key, seeds in results.items():
        for r in seeds:
            for field in ("gains", "std", "payload_b", "payload_c", "payload_b_std"):
                for m, v in getattr(r, field).items():
                    if v is not None:
                        out[f"{key}/{r.seed}/{field}/{m}"] = np.asarray(v)
    return out


@pytest.fixture(scope="module")
def dask_offload_thread() -> None:
    """Start Dask's process-wide offload thread before the test's leak check looks: it lives
    as long as the process, whichever test first talks to a cluster."""
    utils = pytest.importorskip("distributed.utils")
    utils._offload_executor.submit(lambda: None).result()


@pytest.mark.usefixtures("dask_offload_thread")
def test_study_seeds_on_a_dask_cluster_match_the_local_run() -> None:
    """A tiny study (2 seeds of one scenario) through the scheduler's address, against the same
    seeds run here: the same numbers, bit for bit (same code, same seeds, one BLAS thread)."""
    distributed = pytest.importorskip("distributed")
    scenario = [SCENARIOS[2]]  # current noise: the costly estimators all run
    far = time.perf_counter() + 600
    with limited_blas_threads(1):
        world = make_world()
        local = run_monte_carlo(world, 2, far, scenario, progress=lambda _: None)
        with distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=False,  # workers in this process, reached over TCP like a remote cluster
            protocol="tcp",
            host="127.0.0.1",
            dashboard_address=None,
        ) as cluster:
            lines: list[str] = []
            remote = run_monte_carlo(
                world, 2, far, scenario, progress=lines.append, scheduler=cluster.scheduler_address
            )
    assert any(cluster.scheduler_address in line for line in lines)
    assert [r.seed for r in remote[scenario[0].key]] == [0, 1]
    a, b = _numbers(local), _numbers(remote)
    assert a.keys() == b.keys() and len(a) > 20
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_bad_scheduler_addresses_are_refused_before_connecting() -> None:
    world = object()  # never used: the address is checked first
    for address in ("localhost:8786", "tcp://:8786", "tcp://host:port"):
        with pytest.raises(InputError, match="tcp://HOST:PORT"):
            run_monte_carlo(world, 2, 0.0, [], progress=lambda _: None, scheduler=address)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="workers"):
        run_monte_carlo(world, 2, 0.0, [], progress=lambda _: None, workers=0)  # type: ignore[arg-type]
