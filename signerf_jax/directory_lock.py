"""One process at a time in a directory: an OS file lock (`flock`) on a file in it.

The kernel drops the lock when its process ends, however it ends, so a lock left by a killed
run is simply taken by the next one. The file holds the holder's pid, which a refused process
is told.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from signerf_jax.errors import InputError


class DirectoryInUse(InputError):
  """Another process holds the directory's lock."""


def _recorded_holder(descriptor: int) -> str:
  """The pid a lock file records ("unknown" when it records none)."""
  return os.pread(descriptor, 32, 0).decode("ascii", "replace").strip() or "unknown"


def _in_use(held_by: str, path: Path, flag: str, where: str) -> DirectoryInUse:
  return DirectoryInUse(f"is in use by another signerf process (pid {held_by}){where}: wait "
                        "for it to end or stop it", path, flag)


def _holder_text(lock_path: Path) -> str | None:
  """The pid the lock file in `lock_path` records (`_recorded_holder`) while a process holds
  its lock, else None; the lock is tested, not kept."""
  if not lock_path.is_file():
    return None
  descriptor = os.open(lock_path, os.O_RDONLY)
  try:
    try:
      fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
      return None
    except BlockingIOError:
      return _recorded_holder(descriptor)
  finally:
    os.close(descriptor)


def check_free(lock_path: Path, path: Path, flag: str, where: str = "") -> None:
  """Raises DirectoryInUse (naming `path`, `flag` and the holder's pid, then `where`) when
  another process holds the lock in `lock_path`."""
  held_by = _holder_text(lock_path)
  if held_by is not None:
    raise _in_use(held_by, path, flag, where)


def holder(lock_path: Path) -> int | None:
  """The pid of the process holding the lock in `lock_path` (None when none holds it, or its
  pid is not recorded)."""
  held_by = _holder_text(lock_path)
  return int(held_by) if held_by is not None and held_by.isdigit() else None


def hold(lock_path: Path, path: Path, flag: str, where: str = "") -> int:
  """Takes the lock in `lock_path` (created if missing) for this process and writes its pid
  there. Returns the descriptor: closing it releases the lock.

  Raises:
    DirectoryInUse as `check_free`.
  """
  descriptor = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
  try:
    fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except BlockingIOError:
    error = _in_use(_recorded_holder(descriptor), path, flag, where)
    os.close(descriptor)
    raise error from None
  os.ftruncate(descriptor, 0)
  os.pwrite(descriptor, f"{os.getpid()}\n".encode("ascii"), 0)
  return descriptor
