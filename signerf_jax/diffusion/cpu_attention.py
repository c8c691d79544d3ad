"""The fused CPU attention kernel (cpu_attention.cc): built on first use, called through XLA's FFI.

The kernel is C++ with AVX2/FMA intrinsics, compiled here with the system's C++ compiler
(`$CXX`, else `c++`) for this machine (`-march=native`) into a cache folder
(`$SIGNERF_JAX_CACHE`, else `~/.cache/signerf_jax`) under a name that hashes the source, the
jaxlib version, the compiler command and the CPU, so a change of any rebuilds it and machines
sharing a home folder do not share a binary. Where it cannot be built -- not x86-64 Linux, no
AVX2/FMA, no compiler, a compile error -- `load` says why once (a warning) and returns False, and
attention.py keeps to XLA's ops.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import platform
import shlex
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
from jax.custom_batching import custom_vmap
from jax.experimental.custom_partitioning import custom_partitioning
from jax.sharding import NamedSharding, PartitionSpec

from signerf_jax import files

SOURCE = Path(__file__).with_suffix(".cc")
TARGET_NAME = "signerf_cpu_attention"
# Head sizes the kernel takes: whole AVX vectors, and the largest of SD 1.x-XL's (1280 / 8).
HEAD_DIM_MULTIPLE, MAX_HEAD_DIM = 8, 160
COMPILE_FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC")


def _cpu_description() -> str | None:
  """The CPU's model name and flags lines (Linux), or None where /proc/cpuinfo is missing."""
  try:
    lines = Path("/proc/cpuinfo").read_text().splitlines()
  except OSError:
    return None
  wanted = [line for line in lines if line.startswith(("model name", "flags"))]
  return "\n".join(sorted(set(wanted)))


def cache_directory() -> Path:
  """Where built kernels are kept: `$SIGNERF_JAX_CACHE`, else ~/.cache/signerf_jax."""
  return Path(os.environ.get("SIGNERF_JAX_CACHE", Path.home() / ".cache" / "signerf_jax"))


def build(source: str, compiler: Sequence[str] | None = None, cpu: str | None = None) -> Path:
  """A shared library of kernel `source` (the text of a cpu_attention.cc), compiled now unless the
  cache holds it, with `compiler` (default `$CXX`, else `c++`) for `cpu` (default this machine's
  /proc/cpuinfo lines; both are part of the cache key). Written to a temporary file beside its
  final name and renamed (files.atomic_path), so concurrent builds (test workers) never load half
  a file. Raises RuntimeError with the compiler's output when the compile fails."""
  compiler = list(compiler or _compiler())
  cpu = _cpu_description() if cpu is None else cpu
  key = hashlib.sha256("\0".join([source, jaxlib.__version__, *compiler, *COMPILE_FLAGS,
                                  str(cpu)]).encode()).hexdigest()[:16]
  library = cache_directory() / f"cpu_attention-{key}.so"
  if library.exists():
    return library
  with files.atomic_path(library) as temporary:
    command = [*compiler, *COMPILE_FLAGS, f"-I{jax.ffi.include_dir()}", "-x", "c++", "-",
               "-o", str(temporary)]
    done = subprocess.run(command, input=source, capture_output=True, text=True, check=False)
    if done.returncode != 0:
      raise RuntimeError(f"{shlex.join(command)} failed:\n{done.stderr[-2000:]}")
  return library


def register(library: Path, target_name: str = TARGET_NAME) -> None:
  """Loads a built `library` and registers its handler with XLA's CPU backend as `target_name`."""
  handler = ctypes.cdll.LoadLibrary(str(library)).SignerfCpuAttention
  jax.ffi.register_ffi_target(target_name, jax.ffi.pycapsule(handler), platform="cpu")


def _compiler() -> list[str]:
  return shlex.split(os.environ.get("CXX", "c++"))


def unmet_requirement() -> str | None:
  """Why this machine cannot build the kernel (not x86-64 Linux, no AVX2/FMA, no compiler), or
  None where it can try."""
  cpu = _cpu_description()
  compiler = _compiler()[0]
  if platform.system() != "Linux" or platform.machine() != "x86_64" or cpu is None:
    return f"needs x86-64 Linux, not {platform.system()} {platform.machine()}"
  if not {"avx2", "fma"} <= set(cpu.split()):
    return "the CPU lacks AVX2 or FMA"
  if shutil.which(compiler) is None:
    return f"no C++ compiler {compiler!r} (set CXX)"
  return None


@functools.cache
def load() -> bool:
  """Builds (or finds) the kernel and registers it with XLA's CPU backend; False, with one
  warning saying why, where this machine cannot run it."""
  reason = unmet_requirement()
  if reason is None:
    try:
      register(build(SOURCE.read_text()))
    except (OSError, RuntimeError) as error:
      reason = str(error)
    else:
      return True
  logging.warning("signerf_jax: the fused CPU attention kernel is off (%s); attention runs "
                  "through XLA's ops", reason)
  return False


def supports(head_dim: int) -> bool:
  """Whether the kernel takes heads of `head_dim` channels."""
  return head_dim % HEAD_DIM_MULTIPLE == 0 and head_dim <= MAX_HEAD_DIM


def _ffi_attention(query: jax.Array, key: jax.Array, value: jax.Array) -> jax.Array:
  return jax.ffi.ffi_call(TARGET_NAME, jax.ShapeDtypeStruct(query.shape, jnp.float32))(
      query, key, value)


def _kept_sharding(mesh, arg_shapes, result_shape) -> NamedSharding:
  """The query's sharding on its leading (batch) axes and heads; tokens and channels whole."""
  del result_shape
  rank = len(arg_shapes[0].shape)
  spec = (*arg_shapes[0].sharding.spec, *(None,) * rank)[:rank]
  return NamedSharding(mesh, PartitionSpec(*spec[:-3], None, spec[-2], None))


def _partition(mesh, arg_shapes, result_shape):
  sharding = _kept_sharding(mesh, arg_shapes, result_shape)
  return mesh, _ffi_attention, sharding, (sharding,) * 3


# Over several devices each runs the kernel on its own batch entries and heads (without this the
# partitioner would gather the whole batch onto every device and repeat the work there).
_partitioned_attention = custom_partitioning(_ffi_attention)
_partitioned_attention.def_partition(
    partition=_partition, infer_sharding_from_operands=_kept_sharding,
    sharding_rule="... q h d, ... k h d, ... k h d -> ... q h d",
    need_replication_factors=("q", "d", "k"))  # Sorted as the rule first names them.


@custom_vmap
def attention(query: jax.Array, key: jax.Array, value: jax.Array) -> jax.Array:
  """softmax(q k^T) v per head, by the kernel (built and registered first if need be).

  Args:
    query: [..., Tq, H, D] float32, already scaled by 1/sqrt(D); D a multiple of 8 up to 160.
    key, value: [..., Tk, H, D] float32, the same leading (batch) axes.

  Returns:
    [..., Tq, H, D] float32.

  Raises:
    RuntimeError: where `load` cannot build the kernel.
  """
  if not load():
    raise RuntimeError("the fused CPU attention kernel cannot run here (the warning says why)")
  return _partitioned_attention(query, key, value)


@attention.def_vmap
def _attention_vmap(axis_size, in_batched, query, key, value):
  """A vmapped axis is one more leading batch axis, which the kernel takes as it is (custom
  partitioning has no batching rule of its own)."""
  query, key, value = (x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))
                       for x, batched in zip((query, key, value), in_batched))
  return attention(query, key, value), True
