"""Fixtures for the NeRF tests: a tiny analytic scene (helpers in `small_nerf`)."""

from __future__ import annotations

import pytest

from analytic_scene import sphere_dataset


@pytest.fixture(scope="session")
def sphere():
  return sphere_dataset()
