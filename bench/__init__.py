"""Benchmarks, runnable as `quatrack bench NAME`; figures go into bench/RESULTS.md."""
