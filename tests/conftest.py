"""Shared test plumbing: the ../shared/data location, the `shared_data` marker, no persistent
compilation cache, and a broken torchvision hidden from transformers."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# The CLI keeps compiled programs in the user's cache directory between commands; tests (and the
# commands they start) must neither read a machine's cache nor write to it.
os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

REPOSITORY_ROOT = Path(__file__).resolve().parent.parent
# Real scenes and meshes live outside the project; SIGNERF_SHARED_DATA overrides the location.
SHARED_DATA = Path(os.environ.get("SIGNERF_SHARED_DATA", REPOSITORY_ROOT.parent / "shared" / "data"))


def _hide_unloadable_torchvision() -> None:
  """transformers (imported by diffusers) imports torchvision whenever it is installed; a
  torchvision wheel built for another torch (e.g. the CUDA one from PyPI next to the CPU torch)
  then fails to load and breaks every diffusers import. None of these tests needs torchvision, so
  a broken one is made to look absent."""
  try:
    import torchvision  # pylint: disable=g-import-not-at-top,unused-import
  except (ImportError, RuntimeError, OSError):
    for name in [name for name in sys.modules if name.split(".")[0] == "torchvision"]:
      del sys.modules[name]
    sys.modules["torchvision"] = None  # find_spec() now reports it absent.


_hide_unloadable_torchvision()


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
