"""`--dask local` is reachable from this machine only; scheduler addresses are checked."""
from __future__ import annotations

from urllib.parse import urlparse

import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.parallel.settings import ParallelSettings, check_dask_spec


@pytest.mark.parametrize("spec, why", [("http://localhost:8787", "not a Dask scheduler"),
                                       ("tcp://node1", "HOST:PORT"), ("tcp://:8786", "HOST:PORT"),
                                       ("node1", "expected 'local'")])
def test_bad_scheduler_addresses_name_the_flag(spec, why):
    with pytest.raises(InputError, match=why) as e:
        ParallelSettings(dask=spec)
    assert e.value.where == "--dask"
    with pytest.raises(InputError) as e:
        check_dask_spec(spec, "$RELIEF_DASK_SCHEDULER")
    assert e.value.where == "$RELIEF_DASK_SCHEDULER"


def test_good_scheduler_addresses():
    assert check_dask_spec("node1:8786") == "tcp://node1:8786"
    assert check_dask_spec("TLS://node1:8786/") == "tls://node1:8786"
    assert check_dask_spec("local") == "local"


def test_env_scheduler_is_checked_like_the_flag(monkeypatch):
    import relief_bsdf.parallel as parallel
    from relief_bsdf.parallel.cluster import trivial_task
    monkeypatch.setenv("RELIEF_DASK_SCHEDULER", "http://evil.example:80")
    with pytest.raises(InputError, match="RELIEF_DASK_SCHEDULER"):
        parallel.map_tasks(trivial_task, [1, 2], None, backend="dask")


@pytest.mark.slow
def test_local_cluster_binds_to_loopback():
    from relief_bsdf.parallel import cluster
    client = cluster.get_client("local", workers=1)
    try:
        assert urlparse(client.dashboard_link).hostname == "127.0.0.1"
        assert urlparse(client.scheduler.address).hostname == "127.0.0.1"
        workers = client.scheduler_info()["workers"]
        assert workers and all(urlparse(w).hostname == "127.0.0.1" for w in workers)
    finally:
        cluster.close_client("local")
