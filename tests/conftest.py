"""Shared fixtures."""

from __future__ import annotations

import pytest
from shapes import sphere_points


@pytest.fixture(scope="session")
def sphere500():
    return sphere_points(500, seed=1)
