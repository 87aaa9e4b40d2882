"""Until helper C's ``dask_client`` fixture (tests/conftest.py) is merged: the same fixture,
an in-process LocalCluster of two single-thread workers for the session."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest


@pytest.fixture(scope="session")
def dask_client() -> Iterator[Any]:
    from dobhil.cluster import open_client
    with open_client(workers=2, processes=False) as client:
        yield client
