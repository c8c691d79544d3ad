"""Shared test plumbing: the ../shared/data location and the `shared_data` marker."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPOSITORY_ROOT = Path(__file__).resolve().parent.parent
# Real scenes and meshes live outside the project; SIGNERF_SHARED_DATA overrides the location.
SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA", REPOSITORY_ROOT.parent / "shared" / "data"))


def pytest_collection_modifyitems(config, items):
  if SHARED_DATA.is_dir():
    return
  skip = pytest.mark.skip(reason=f"needs the real data in {SHARED_DATA} (absent on this machine)")
  for item in items:
    if "shared_data" in item.keywords:
      item.add_marker(skip)


@pytest.fixture(scope="session")
def shared_data() -> Path:
  """The ../shared/data directory; tests using it must carry @pytest.mark.shared_data."""
  return SHARED_DATA
