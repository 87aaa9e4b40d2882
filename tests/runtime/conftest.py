"""Fixtures of the runtime tests."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from .hub import serve_hub


@pytest.fixture
def hub(tmp_path: Path) -> Iterator[int]:
    """A python-can-remote hub on 127.0.0.1 serving a virtual channel; yields its port."""
    yield from serve_hub(tmp_path)
