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


def _in_use(descriptor: int, path: Path, flag: str, where: str) -> DirectoryInUse:
  holder = os.pread(descriptor, 32, 0).decode("ascii", "replace").strip() or "unknown"
  return DirectoryInUse(f"is in use by another signerf process (pid {holder}){where}: wait "
                        "for it to end or stop it", path, flag)


def check_free(lock_path: Path, path: Path, flag: str, where: str = "") -> None:
  """Raises DirectoryInUse (naming `path`, `flag` and the holder's pid, then `where`) when
  another process holds the lock in `lock_path`; the lock is tested, not kept."""
  if not lock_path.is_file():
    return
  descriptor = os.open(lock_path, os.O_RDONLY)
  try:
    try:
      fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
      raise _in_use(descriptor, path, flag, where) from None
  finally:
    os.close(descriptor)


def holder(lock_path: Path) -> int | None:
  """The pid of the process holding the lock in `lock_path`, or None when none holds it."""
  if not lock_path.is_file():
    return None
  descriptor = os.open(lock_path, os.O_RDONLY)
  try:
    try:
      fcntl.flock(descriptor, fcntl.LOCK_SH | fcntl.LOCK_NB)
      return None
    except BlockingIOError:
      text = os.pread(descriptor, 32, 0).decode("ascii", "replace").strip()
      return int(text) if text.isdigit() else None
  finally:
    os.close(descriptor)


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
    error = _in_use(descriptor, path, flag, where)
    os.close(descriptor)
    raise error from None
  os.ftruncate(descriptor, 0)
  os.pwrite(descriptor, f"{os.getpid()}\n".encode("ascii"), 0)
  return descriptor
