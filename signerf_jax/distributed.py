"""One command run by several processes (several hosts, or several processes of one), joined
through `jax.distributed`, and what each of them writes.

A command joins when given `--coordinator_address HOST:PORT --num_processes P --process_id I`
(or the environment variables in ENVIRONMENT, as cluster launchers set them per process). Every
process then runs the same program on the devices of all of them (`parallel`): a NeRF step's
batch and the image set update's views are split over every device. Only process 0 writes the
command's outputs and prints its results. Each other process works in a private copy of the
output directory, taken before any process writes and removed when the command ends, so that
it reads back what it wrote itself and never races process 0 for a file. Resuming therefore
needs the output directory on a filesystem every host sees (a new run needs only the inputs
shared).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import jax
import numpy as np

from signerf_jax import parallel
from signerf_jax.errors import InputError

# flag -> the environment variable that gives it when the flag is absent.
ENVIRONMENT = {"coordinator_address": "SIGNERF_COORDINATOR_ADDRESS",
               "num_processes": "SIGNERF_NUM_PROCESSES", "process_id": "SIGNERF_PROCESS_ID"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
  """--coordinator_address, --num_processes, --process_id (see the module docstring)."""
  group = parser.add_argument_group("several processes (jax.distributed)")
  group.add_argument("--coordinator_address", default=None, metavar="HOST:PORT",
                     help="join a run of several processes whose process 0 listens at HOST:PORT "
                     f"(default: ${ENVIRONMENT['coordinator_address']}, else one process)")
  group.add_argument("--num_processes", type=int, default=None,
                     help=f"how many processes take part (default: "
                     f"${ENVIRONMENT['num_processes']}, else 1)")
  group.add_argument("--process_id", type=int, default=None,
                     help=f"this process's index among them (default: "
                     f"${ENVIRONMENT['process_id']}, else 0); only process 0 writes outputs")


def settings(args: argparse.Namespace) -> tuple[str, int, int] | None:
  """(coordinator address, process count, process index) from the flags, else the environment;
  None when neither names a coordinator."""
  values = {}
  for name, variable in ENVIRONMENT.items():
    value = getattr(args, name, None)
    values[name] = os.environ.get(variable) if value is None else value
  if not values["coordinator_address"]:
    return None
  numbers = {}
  for name in ("num_processes", "process_id"):
    try:
      numbers[name] = int(values[name])
    except (TypeError, ValueError):
      raise InputError(f"a run of several processes needs it as a whole number (flag or "
                       f"${ENVIRONMENT[name]}), got {values[name]!r}", field=name) from None
  return values["coordinator_address"], numbers["num_processes"], numbers["process_id"]


@contextlib.contextmanager
def private_outputs(args: argparse.Namespace, flag: str | None) -> Iterator[None]:
  """Runs a command's body as this process should in a run of several (module docstring):
  process 0 as usual; any other with `args.<flag>` pointed at a private copy of the output
  directory and its output (results, progress bars, warnings) discarded: an error still
  reaches stderr, reported after the block. Every process waits here until the others have
  taken their copies. One process: nothing changes."""
  if jax.process_count() == 1:
    yield
    return
  if jax.process_index() == 0 or flag is None:
    parallel.barrier("signerf: outputs copied")
    yield
    return
  scratch = Path(tempfile.mkdtemp(prefix=f"signerf-process-{jax.process_index()}-"))
  try:
    copy = scratch / "outputs"
    original = getattr(args, flag, None)
    if original and Path(original).is_dir():
      shutil.copytree(original, copy, symlinks=True)
    setattr(args, flag, str(copy))
    parallel.barrier("signerf: outputs copied")
    with open(os.devnull, "w", encoding="utf-8") as discard, \
        contextlib.redirect_stdout(discard), contextlib.redirect_stderr(discard):
      yield
  finally:
    shutil.rmtree(scratch, ignore_errors=True)


def to_host(tree: Any) -> Any:
  """Every leaf of `tree` as a NumPy array on this host: arrays spread over the devices of
  several processes are gathered from all of them first (`jax.device_get` fetches only what
  this process holds: a whole array, or one fully replicated)."""
  def fetch(leaf):
    if isinstance(leaf, jax.Array) and not (leaf.is_fully_addressable
                                            or leaf.is_fully_replicated):
      from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
      return np.asarray(multihost_utils.process_allgather(leaf, tiled=True))
    return np.asarray(jax.device_get(leaf)) if isinstance(leaf, jax.Array) else leaf
  return jax.tree.map(fetch, tree)
