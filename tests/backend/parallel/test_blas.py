"""parallel.blas: pool workers run their BLAS on one thread; a process computing beside them can for a block."""
from threadpoolctl import threadpool_info

import relief_bsdf.parallel as parallel
from relief_bsdf.parallel import blas


def _blas_threads(context, task):
    import numpy.linalg  # noqa: F401  (numpy's OpenBLAS)
    import scipy.linalg  # noqa: F401  (scipy's own OpenBLAS)
    return sorted({d["num_threads"] for d in threadpool_info() if d.get("user_api") == "blas"})


def test_pool_workers_run_their_blas_on_one_thread():
    """Before parallel.blas a worker's OpenBLAS kept one thread per core (its OMP_NUM_THREADS came after
    numpy had loaded it): on the 2-core machine two spinning threads per worker beside the main process."""
    out = parallel.map_tasks(_blas_threads, [0, 1, 2, 3], None, backend="processes", workers=2)
    assert out == [[1]] * 4


def test_blas_single_thread_limits_this_process_for_the_block_only():
    before = _blas_threads(None, None)
    with blas.blas_single_thread():
        assert _blas_threads(None, None) == [1]
    assert _blas_threads(None, None) == before


def test_workers_one_blas_thread_sets_what_is_unset_and_leaves_a_users_setting(monkeypatch):
    import os
    for name in blas.BLAS_THREAD_ENV:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "3")
    blas.workers_one_blas_thread()
    assert os.environ["OPENBLAS_NUM_THREADS"] == "3"
    assert all(os.environ[n] == "1" for n in blas.BLAS_THREAD_ENV if n != "OPENBLAS_NUM_THREADS")
