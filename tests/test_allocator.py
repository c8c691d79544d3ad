"""signerf_jax.allocator: freed memory stays mapped, so allocating it again costs no page faults.

The real settings change the process's allocator for good, so they are tried in child processes;
they count page faults (deterministic), never time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from signerf_jax import allocator

BLOCK_BYTES = 128 * 2**20  # Above glibc's mmap threshold and a thread arena's 64-MiB heap.
PAGES = BLOCK_BYTES // 4096

# A child that (maybe) keeps freed memory, then from a worker thread (XLA allocates from its
# worker threads) allocates, touches and frees the block five times; it prints the setting and
# the minor page faults of the last four rounds (the first maps the memory either way).
CHILD = f"""
import ctypes, json, resource, threading
from signerf_jax import allocator
kept = allocator.keep_freed_memory()
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
faults = []
def rounds():
  for _ in range(5):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = libc.malloc({BLOCK_BYTES})
    ctypes.memset(block, 1, {BLOCK_BYTES})
    libc.free(block)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
thread = threading.Thread(target=rounds)
thread.start()
thread.join()
print(json.dumps({{"kept": kept, "again": allocator.keep_freed_memory(), "faults": faults[1:]}}))
"""

needs_glibc = pytest.mark.skipif(allocator._glibc() is None,  # pylint: disable=protected-access
                                 reason="the settings are glibc's")


def run_child(setting: str) -> dict:
  environment = {**os.environ, allocator.ENVIRONMENT_VARIABLE: setting}
  completed = subprocess.run([sys.executable, "-c", CHILD], env=environment, check=True,
                             capture_output=True, text=True)
  return json.loads(completed.stdout)


@needs_glibc
def test_freed_memory_is_reused_without_page_faults():
  child = run_child("1")
  assert child["kept"] and child["again"]
  # Each round would touch PAGES fresh pages if the block went back to the kernel.
  assert max(child["faults"]) < PAGES // 100, child


@needs_glibc
def test_the_environment_can_leave_the_allocator_as_it_was():
  child = run_child("0")
  assert not (child["kept"] or child["again"])
  # With glibc's defaults the block is mapped afresh each round: one fault per page, or per
  # huge page where the host backs anonymous memory with them (transparent huge pages: always).
  assert min(child["faults"]) >= PAGES // 512, child


def test_without_glibc_nothing_changes(monkeypatch):
  monkeypatch.setattr(allocator, "_glibc", lambda: None)
  monkeypatch.setattr(allocator, "_kept", False)
  monkeypatch.delenv(allocator.ENVIRONMENT_VARIABLE, raising=False)
  assert not allocator.keep_freed_memory()


class RecordingLibrary:
  """Stands in for glibc: records each `mallopt` call and accepts it."""

  def __init__(self):
    self.calls = []

  def mallopt(self, option, value):
    self.calls.append((option, value))
    return 1


@pytest.mark.parametrize("backend, kept", [("cpu", True), ("gpu", False), ("tpu", False)])
def test_freed_memory_is_kept_on_cpus_only(monkeypatch, backend, kept):
  """XLA:CPU's buffers come from `malloc`; a GPU's or TPU's are the device's memory."""
  library = RecordingLibrary()
  monkeypatch.setattr(allocator, "_glibc", lambda: library)
  monkeypatch.setattr(allocator, "_kept", False)
  monkeypatch.delenv(allocator.ENVIRONMENT_VARIABLE, raising=False)
  assert allocator.keep_freed_memory(backend) == kept
  assert library.calls == (list(allocator.SETTINGS) if kept else [])


def test_without_a_backend_it_is_read_before_jax_starts(monkeypatch):
  library = RecordingLibrary()
  monkeypatch.setattr(allocator, "_glibc", lambda: library)
  monkeypatch.setattr(allocator, "_kept", False)
  monkeypatch.delenv(allocator.ENVIRONMENT_VARIABLE, raising=False)
  monkeypatch.setattr(allocator, "backend_before_start", lambda: "gpu")
  assert not allocator.keep_freed_memory() and not library.calls


@pytest.mark.parametrize("platforms, expected", [
    ("cpu", "cpu"), ("cuda", "gpu"), ("rocm,cpu", "gpu"), ("tpu", "tpu"), (" CPU , cuda", "cpu")])
def test_jax_platforms_names_the_backend(monkeypatch, platforms, expected):
  monkeypatch.setenv("JAX_PLATFORMS", platforms)
  assert allocator.backend_before_start() == expected


@pytest.mark.parametrize("libtpu, plugins, expected", [
    (False, False, "cpu"), (False, True, "gpu"), (True, False, "tpu"), (True, True, "tpu")])
def test_installed_accelerator_packages_name_the_backend(monkeypatch, libtpu, plugins, expected):
  """Without JAX_PLATFORMS, JAX takes an accelerator whose package is installed."""
  monkeypatch.delenv("JAX_PLATFORMS", raising=False)
  real_find_spec = allocator.importlib.util.find_spec
  monkeypatch.setattr(allocator.importlib.util, "find_spec",
                      lambda name: (object() if libtpu else None) if name == "libtpu"
                      else real_find_spec(name))
  monkeypatch.setattr(allocator, "_jax_plugins_installed", lambda: plugins)
  assert allocator.backend_before_start() == expected
