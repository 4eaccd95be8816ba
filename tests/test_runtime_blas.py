"""BLAS thread limit: applied to the loaded BLAS libraries, and never over the user's own settings."""

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from quatrack.recognition.runtime import _BLAS_ENV, limit_blas_threads


@pytest.fixture
def clean_env(monkeypatch):
    for v in _BLAS_ENV:
        monkeypatch.delenv(v, raising=False)
    with threadpool_limits(None):  # whatever the test sets is undone afterwards
        yield monkeypatch


def test_applied_to_numpys_blas(clean_env):
    assert np.ones((4, 4)) @ np.ones(4) is not None  # numpy's BLAS is loaded
    assert limit_blas_threads(1) is True
    blas = [i for i in threadpool_info() if i["user_api"] == "blas"]
    assert blas and all(i["num_threads"] == 1 for i in blas)
    import os

    assert os.environ["OPENBLAS_NUM_THREADS"] == "1"  # for BLAS libraries loaded later
    with pytest.raises(ValueError):
        limit_blas_threads(0)


@pytest.mark.parametrize("var", ["OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"])
def test_users_environment_wins(clean_env, var):
    clean_env.setenv(var, "2")
    before = [i["num_threads"] for i in threadpool_info()]
    assert limit_blas_threads(1) is False
    assert [i["num_threads"] for i in threadpool_info()] == before
