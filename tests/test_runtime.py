"""Allocator tuning: applied on glibc, and never over the user's own MALLOC_* settings."""

import platform

import pytest

from quatrack.recognition.runtime import tune_allocator


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_applied_on_glibc(monkeypatch):
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert tune_allocator() is True
    with pytest.raises(ValueError):
        tune_allocator(trim_threshold=1 << 40)


def test_users_environment_wins(monkeypatch):
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "0")
    assert tune_allocator() is False
