"""Makes the C allocator keep the memory a jitted call frees, so the next call reuses it.

XLA:CPU allocates each call's outputs and temporary buffers with `malloc` and frees them when the
call returns. glibc gives large blocks (above its mmap threshold, at most 32 MiB, and anything
over 64 MiB that a worker thread's arena cannot hold) back to the kernel on `free`, so the next
call's buffers arrive as fresh pages that the kernel maps and zeroes one 4-KiB page fault at a
time. A NeRF training step frees and re-faults hundreds of MiB every step, and on a CPU with
few cores that kernel time is a large share of NeRF training (docs/performance.md).

`keep_freed_memory()` sets glibc's `mallopt` so that every thread allocates from the one main
heap, large blocks come from that heap instead of `mmap`, and the heap is trimmed only past
2 GiB of free space at its top. Freed pages then stay mapped and are reused; the results are the
same bytes. The costs: the process keeps the memory it has used (its peak, plus what
fragmentation adds) until it exits, and the diffusion sampler and XLA's compiler run slower:
their threads contend for the one heap, and large blocks served from the heap are slower too
(docs/performance.md). So the commands that train or render a NeRF call it first thing
(`signerf_jax.cli.keeps_freed_memory`; the viewer too, whose frames are NeRF renders), the
edit commands run their NeRF trainings in a child process that calls it
(`editing.commands.training_process`), and library code never does.
SIGNERF_KEEP_FREED_MEMORY=0 in the environment leaves the allocator as it was. Elsewhere than
glibc (macOS, musl) it does nothing, and so it does where JAX computes on a GPU or TPU: their
buffers are the device's memory, not `malloc`'s, and the setting was measured on CPUs only. The
backend is read before JAX starts it (`backend_before_start`), since starting it starts the
threads whose arenas the setting must precede.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import importlib.util
import os
import pkgutil

# glibc's malloc.h parameter numbers.
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8
SETTINGS = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1))
ENVIRONMENT_VARIABLE = "SIGNERF_KEEP_FREED_MEMORY"
# JAX_PLATFORMS's names of GPU platforms (JAX's backend name for all of them is "gpu").
GPU_PLATFORMS = ("cuda", "rocm", "gpu")

_kept = False


def _glibc() -> ctypes.CDLL | None:
  """The process's C library when it is glibc (it has `mallopt`), else None."""
  try:
    library = ctypes.CDLL(None)
  except OSError:
    return None
  if not (hasattr(library, "gnu_get_libc_version") and hasattr(library, "mallopt")):
    return None
  library.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
  library.mallopt.restype = ctypes.c_int
  return library


def _jax_plugins_installed() -> bool:
  """Whether a PJRT plugin is installed for JAX to load (CUDA's, ROCm's...): a module of the
  `jax_plugins` namespace package or an entry point of that group, as JAX finds them."""
  if importlib.metadata.entry_points(group="jax_plugins"):
    return True
  namespace = importlib.util.find_spec("jax_plugins")
  locations = namespace.submodule_search_locations if namespace is not None else None
  return bool(locations) and any(True for _ in pkgutil.iter_modules(locations))


def backend_before_start() -> str:
  """The backend JAX will compute on, found without starting JAX: the first platform named in
  JAX_PLATFORMS ("cpu", "gpu" for CUDA or ROCm, "tpu"); without one, "tpu" where libtpu is
  installed, "gpu" where a JAX plugin is, else "cpu". An accelerator's package on a machine
  without the accelerator makes JAX fall back to the CPU while this says the accelerator:
  freed memory is then not kept, which is slower, not wrong."""
  platforms = os.environ.get("JAX_PLATFORMS", "").strip().lower()
  if platforms:
    first = platforms.split(",")[0].strip()
    return "gpu" if first in GPU_PLATFORMS else first
  if importlib.util.find_spec("libtpu") is not None:
    return "tpu"
  return "gpu" if _jax_plugins_installed() else "cpu"


def can_keep_freed_memory(backend: str | None = None) -> bool:
  """Whether `keep_freed_memory` applies its settings in a process computing on `backend` (None:
  `backend_before_start()`): a CPU, with glibc, and the environment does not say 0."""
  if os.environ.get(ENVIRONMENT_VARIABLE, "1").strip() == "0":
    return False
  return (backend or backend_before_start()) == "cpu" and _glibc() is not None


def keeps_freed_memory() -> bool:
  """Whether this process keeps freed memory (`keep_freed_memory` applied its settings)."""
  return _kept


def keep_freed_memory(backend: str | None = None) -> bool:
  """Applies the settings above where `can_keep_freed_memory(backend)`; returns whether the
  process now keeps freed memory. Call it before JAX starts its threads (their arenas exist
  from then on); calling it again changes nothing."""
  global _kept
  if _kept or not can_keep_freed_memory(backend):
    return _kept
  library = _glibc()
  _kept = all([library.mallopt(option, value) == 1 for option, value in SETTINGS])
  return _kept
