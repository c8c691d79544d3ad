"""Shared test plumbing: the ../shared/data location, the `shared_data` marker, a compilation
cache private to the session, XLA's optimisation level, glibc's allocator left as it is, a broken
torchvision hidden from transformers, compiled programs released before they use up the
process's memory maps, and experiment scripts imported as modules."""

from __future__ import annotations

import gc
import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path

import gin
import pytest

# The CLI keeps compiled programs in the user's cache directory between commands; tests (and the
# commands they start) must neither read a machine's cache nor write to it. Many tests compile
# the same programs again (a NeRF step, a tiny pipeline, in-process and in the commands they
# start), so they share a cache that lives as long as the session (a tenth of the suite's
# time); JAX_ENABLE_COMPILATION_CACHE=false turns it off. Under pytest-xdist the controller
# makes it and its workers, which inherit the controller's environment, share it (an entry one
# worker reads while the other is still writing it fails to decompress: JAX warns and compiles).
SESSION_CACHE_VARIABLE = "SIGNERF_TESTS_COMPILATION_CACHE"
OWNS_SESSION_CACHE = SESSION_CACHE_VARIABLE not in os.environ
if OWNS_SESSION_CACHE:
  os.environ[SESSION_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="signerf_jax_tests_xla_")
SESSION_COMPILATION_CACHE = os.environ[SESSION_CACHE_VARIABLE]
os.environ["JAX_COMPILATION_CACHE_DIR"] = SESSION_COMPILATION_CACHE
os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "true")
# Most of the suite's time is compiling. XLA's backend optimisation level 1 instead of its
# default 2 compiles the tiny model's train steps ~30% faster, with results the tests accept
# alike. Only the tests use it: the commands' long runs are run-bound, and it did not run a
# NeRF faster (level 0 compiles faster still, but runs the NeRF fixtures 3x slower and changes
# an exact-equality result: README, "Tests"). Commands the tests start inherit it.
XLA_OPTIMIZATION_LEVEL_FLAG = "--xla_backend_optimization_level"
if XLA_OPTIMIZATION_LEVEL_FLAG not in os.environ.get("XLA_FLAGS", ""):
  os.environ["XLA_FLAGS"] = (f"{os.environ.get('XLA_FLAGS', '')} "
                             f"{XLA_OPTIMIZATION_LEVEL_FLAG}=1").strip()
# `signerf_jax.cli.main` makes its process keep freed memory (signerf_jax.allocator); many tests
# run it inside the test process, whose memory use should not depend on which test ran first.
os.environ.setdefault("SIGNERF_KEEP_FREED_MEMORY", "0")

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


# The test folder whose modules share an expensive session fixture, kept on one worker.
SHARED_FIXTURE_FOLDER = "tests/viewer/"


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
  """`--dist loadscope` (the README's command), with the viewer's modules as one unit.

  xdist hands whole modules to the workers, so a session fixture is built once per worker that
  runs a module using it. The viewer's three modules share a trained NeRF (`viewer/conftest.py`,
  about 90 s of a worker's time); as one unit they build it once, not once per worker.
  """
  if config.getoption("dist", None) != "loadscope":
    return None
  from xdist.scheduler import LoadScopeScheduling  # pylint: disable=g-import-not-at-top

  class SharedFixtureScheduling(LoadScopeScheduling):

    def _split_scope(self, nodeid: str) -> str:
      if nodeid.startswith(SHARED_FIXTURE_FOLDER):
        return SHARED_FIXTURE_FOLDER
      return super()._split_scope(nodeid)

  return SharedFixtureScheduling(config, log)


def _memory_map_count() -> int | None:
  """How many memory mappings this process holds; None where the kernel does not say."""
  try:
    with open("/proc/self/maps", "rb") as maps:
      return sum(1 for _ in maps)
  except OSError:
    return None


def _memory_map_limit() -> int:
  try:
    return int(Path("/proc/sys/vm/max_map_count").read_text())
  except (OSError, ValueError):
    return 65530  # Linux's default.


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
  """Drops JAX's compiled programs after a module when they hold half the process's allowed
  memory maps. Each program's machine code lives in a few maps of its own and JAX keeps every
  program it compiled; a test worker runs hundreds of modules, and near the end of the suite it
  reached the kernel's limit (vm.max_map_count), where LLVM aborts the next compilation."""
  yield
  count = _memory_map_count()
  if count is not None and count > _memory_map_limit() // 2:
    import jax  # pylint: disable=g-import-not-at-top  (after the environment above is set)
    jax.clear_caches()
    gc.collect()


def pytest_sessionfinish(session, exitstatus):
  if OWNS_SESSION_CACHE:
    shutil.rmtree(SESSION_COMPILATION_CACHE, ignore_errors=True)


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


@pytest.fixture(scope="session")
def experiment_script():
  """A loader: `experiment_script(name)` is experiments/<name>.py imported as the module
  `<name>_experiment`, once per session (the scripts are not a package). It is registered in
  sys.modules before it runs, so that its dataclasses resolve their annotations, and runs with
  gin unlocked, so that its configurables register even after a test finalized gin's config."""

  def load(name: str):
    module_name = f"{name}_experiment"
    if module_name not in sys.modules:
      spec = importlib.util.spec_from_file_location(
          module_name, REPOSITORY_ROOT / "experiments" / f"{name}.py")
      sys.modules[module_name] = importlib.util.module_from_spec(spec)
      try:
        with gin.unlock_config():
          spec.loader.exec_module(sys.modules[module_name])
      except BaseException:
        del sys.modules[module_name]
        raise
    return sys.modules[module_name]

  return load
