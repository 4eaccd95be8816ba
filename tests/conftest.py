"""Test-wide configuration: hypothesis profiles.

Why profiles: a property test that draws fresh random examples on every run, and then replays a
failure from ``.hypothesis/``, passes or fails depending on the machine's history. CI must give
the same verdict on every fresh clone, while a developer should keep exploring new examples.

- ``ci`` (selected when the ``CI`` environment variable is set): derandomized — the examples are
  a function of the test alone — no example database, no deadline (a deadline is a timing
  assertion: it fails on a busy machine, not on a bug).
- ``dev`` (the default otherwise): random examples, the local database replays past failures,
  no deadline either.
- ``explore``: ``dev`` with many more examples, to hunt for flaws before they reach CI:
  ``HYPOTHESIS_PROFILE=explore .venv/bin/pytest -q tests/test_adjust.py``.

``HYPOTHESIS_PROFILE`` overrides the choice. Tests state a ``max_examples`` only where an
example is expensive (a network round trip); elsewhere the profile decides.
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", deadline=None, print_blob=True)
settings.register_profile("explore", deadline=None, print_blob=True, max_examples=2000,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE") or ("ci" if os.environ.get("CI") else "dev"))
