"""The record of the files the project wrote in a directory it claimed (`ownership`): one JSON
line a write, ["w", path, temporary...] appended before the file or its temporary appears, or a
removal, ["r", path]; paths relative to the directory, POSIX. Each record is on disk before the
caller goes on, so a kill at any moment leaves a record that names every file it made.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path


def write_atomically(path: Path, text: str) -> None:
  """Writes `path` through a temporary file beside it (fsync, rename)."""
  temporary = path.with_name(f".{path.name}.{secrets.token_hex(4)}")
  with open(temporary, "w", encoding="utf-8") as handle:
    handle.write(text)
    handle.flush()
    os.fsync(handle.fileno())
  os.replace(temporary, path)


def read(log: Path) -> tuple[set[str], set[str]]:
  """(files written, temporary files named) by the records in `log` (none when it is missing).
  A record cut short by a kill is skipped: its file was not yet created."""
  written, temporaries = set(), set()
  if not log.is_file():
    return written, temporaries
  for line in log.read_text(encoding="utf-8", errors="replace").splitlines():
    try:
      operation, relative, *temporary = json.loads(line)
    except (ValueError, TypeError):
      continue
    if operation == "w":
      written.add(relative)
      temporaries.update(temporary)
    elif operation == "r":
      written.discard(relative)
  return written, temporaries


def clean_and_compact(root: Path, log: Path) -> set[str]:
  """Removes the temporary files of writes a kill interrupted (their recorded names under
  `root` only) and rewrites `log` as the files written that still exist (a file the project
  wrote and the user removed is not the project's any more). Returns those files."""
  written, temporaries = read(log)
  for relative in temporaries:
    with contextlib.suppress(FileNotFoundError, IsADirectoryError):
      (root / relative).unlink()
  written = {relative for relative in written if (root / relative).is_file()}
  write_atomically(log, "".join(json.dumps(["w", relative]) + "\n" for relative in sorted(written)))
  return written


def append(descriptor: int, record: list[str]) -> None:
  """Adds `record` to the log open (for appending) as `descriptor`, on disk before returning."""
  os.write(descriptor, (json.dumps(record) + "\n").encode("utf-8"))
  os.fsync(descriptor)
