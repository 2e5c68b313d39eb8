"""Shared fixtures: one default town per test session (generation takes about a second)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


@pytest.fixture(scope="session")
def town():
    from towndrive.sim.world import WorldConfig, cached_town

    return cached_town(WorldConfig().town, 0)
