"""What the project owns on disk: its output directories, the files it wrote in them, and one
process at a time in each.

Every command claims the directory it writes (`claimed(path, kind)`) before its first write.
The claim
  - refuses a directory that exists, holds files and was not made by signerf, and one that is,
    lies inside or holds one of the command's inputs (`check_claimable` does these checks
    alone, before any work);
  - marks a new directory as the project's (`.signerf/owner.json`: its kind, e.g. "run");
  - locks it for this process (`.signerf/lock`: `directory_lock`);
  - removes the temporary files a killed run left behind, by their recorded names.
While a directory is claimed, `files.atomic_path` records each write before the file appears
(`prepare_write`: `.signerf/written.log`, one JSON line) and never replaces an unrecorded file;
`remove_written` deletes recorded files only. The project knows its files by this record, never
by a name or a folder: a user's `notes.txt` or `selection/my.json` beside them stays. A directory
inside a claimed one (an edit's original/ run) belongs to the outer claim; claims nest. A child
process the claiming process waits for may join its claim (`joined`; an edit's NeRF trainings
run in one): it records its writes in the same log, and the parent reads them back (`refresh`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import secrets
import threading
import time
from pathlib import Path
from typing import Iterable, Iterator

from signerf_jax import directory_lock, written_log
from signerf_jax.errors import InputError

MARKER_FOLDER = ".signerf"
OWNER_FILE = "owner.json"
LOG_FILE = "written.log"
LOCK_FILE = "lock"
FORMAT_VERSION = 1
# The kinds of directory a command writes (owner.json's "kind"), and the flags the commands name
# them by (`signerf_jax.cli`; refusals name them): the other kinds are --out.
RUN, EDIT, DATASET, RENDERS, DEMO = "run", "edit", "dataset", "renders", "demo"
FLAGS = {RUN: "run", EDIT: "edit"}
# Names shown in a refusal (at most this many of a directory's files).
LISTED_FILES = 3


@dataclasses.dataclass
class _Claim:
  """A directory this process has claimed: its lock, its record and how often it is claimed."""

  root: Path  # Resolved (symbolic links followed).
  kind: str
  lock_descriptor: int | None  # None: a child's claim, whose lock its parent holds.
  log_descriptor: int
  written: set[str]  # Recorded files, as POSIX paths relative to the root.
  depth: int = 1


_claims: dict[Path, _Claim] = {}
_mutex = threading.RLock()


def _marker(root: Path, name: str) -> Path:
  return root / MARKER_FOLDER / name


def _write_marker(root: Path, name: str, text: str) -> None:
  """Writes one of the marker folder's files atomically."""
  path = _marker(root, name)
  path.parent.mkdir(exist_ok=True)
  written_log.write_atomically(path, text)


def owner_root(path: str | os.PathLike) -> Path | None:
  """The directory made by signerf that holds `path` (itself or its nearest such ancestor,
  symbolic links followed), or None."""
  resolved = Path(path).resolve()
  for candidate in (resolved, *resolved.parents):
    if _marker(candidate, OWNER_FILE).is_file():
      return candidate
  return None


def owner_kind(root: Path) -> str:
  """The kind recorded in a claimed directory's owner.json ("" when unreadable)."""
  try:
    return str(json.loads(_marker(root, OWNER_FILE).read_text(encoding="utf-8")).get("kind", ""))
  except (OSError, ValueError, AttributeError):
    return ""


def _belongs(root: Path, path: Path) -> str:
  """Where a directory inside another's claim belongs, for errors ("" for the root itself)."""
  return "" if root == path.resolve() else f" (it belongs to {root})"


def _listing(directory: Path) -> str:
  names = sorted(path.name for path in directory.iterdir())
  shown = ", ".join(names[:LISTED_FILES])
  return shown + (f" and {len(names) - LISTED_FILES} more" if len(names) > LISTED_FILES else "")


def check_output_path(path: str | os.PathLike, flag: str = "out") -> None:
  """Refuses an output directory that names a file, or lies under one or under a directory this
  process cannot write (nothing is created here): an InputError naming the path and the flag."""
  path = Path(path)
  if path.exists() and not path.is_dir():
    raise InputError("names a file, not a directory", path, flag)
  existing = path
  while not existing.exists():
    existing = existing.parent
  if not existing.is_dir():
    raise InputError(f"cannot be created: {existing} is a file", path, flag)
  if not os.access(existing, os.W_OK | os.X_OK):
    raise InputError(f"cannot be written: {existing} is not writable", path, flag)


def check_claimable(path: str | os.PathLike, kind: str, *,
                    inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
                    flag: str | None = None) -> None:
  """Raises, without touching the disk, what `claimed(path, kind, ...)` would refuse.

  Args:
    path: the output directory.
    kind: what the command writes there (RUN, EDIT, DATASET, RENDERS or DEMO).
    inputs: (flag, path) of what the command reads; None paths are skipped.
    flag: the output's flag, named in errors (default: the kind's, `FLAGS`, else "out").
  Raises:
    InputError naming the path and the flag: a file, not writable, another kind of signerf
      directory, a directory of files signerf did not write, or one overlapping an input;
      directory_lock.DirectoryInUse: another process holds its lock.
  """
  path, flag = Path(path), flag or FLAGS.get(kind, "out")
  check_output_path(path, flag)
  resolved = path.resolve()
  for input_flag, input_path in inputs:
    if input_path is None or str(input_path) == "":
      continue
    given = Path(input_path).resolve()
    relation = ("is" if given == resolved else "lies inside" if given in resolved.parents
                else "holds" if resolved in given.parents else None)
    if relation:
      raise InputError(f"{relation} the input given as --{input_flag} ({input_path}): a command "
                       "never writes into what it reads; choose another directory", path, flag)
  with _mutex:
    if _active_claim(resolved) is not None:
      return  # Claimed by this process already (a command's stages claim again).
  root = owner_root(resolved)
  if root is None:
    if resolved.is_dir() and any(resolved.iterdir()):
      raise InputError(f"holds files signerf did not write ({_listing(resolved)}); nothing "
                       "there is touched: give a new or empty directory", path, flag)
    return
  if root == resolved and owner_kind(root) != kind:
    article = "an" if kind[0] in "aeiou" else "a"
    raise InputError(f"is a signerf {owner_kind(root) or 'unknown'} directory, not {article} "
                     f"{kind} directory: give another", path, flag)
  directory_lock.check_free(_marker(root, LOCK_FILE), path, flag, _belongs(root, path))


@contextlib.contextmanager
def claimed(path: str | os.PathLike, kind: str, *,
            inputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
            flag: str | None = None) -> Iterator[Path]:
  """Claims `path` for this process while the block runs (see the module docstring): checks it
  (`check_claimable`), creates and marks it if new, locks it, removes its recorded temporary
  files. Claims nest: within a claim, a claim of it or of a directory inside it only counts.

  Yields:
    `path` (created).
  """
  inputs = tuple(inputs)
  claim = _claim(Path(path), kind, inputs, flag)
  try:
    Path(path).mkdir(parents=True, exist_ok=True)
    yield Path(path)
  finally:
    _release(claim)


def _claim(path: Path, kind: str, inputs, flag: str | None) -> _Claim:
  check_claimable(path, kind, inputs=inputs, flag=flag)
  flag = flag or FLAGS.get(kind, "out")
  resolved = path.resolve()
  with _mutex:
    active = _active_claim(resolved)
    if active is not None:
      active.depth += 1
      return active
    root = owner_root(resolved)
    if root is None:
      resolved.mkdir(parents=True, exist_ok=True)
      _write_marker(resolved, OWNER_FILE, json.dumps(
          {"kind": kind, "format": FORMAT_VERSION,
           "created": time.strftime("%Y-%m-%d %H:%M:%S")}) + "\n")
      root = resolved
    lock = directory_lock.hold(_marker(root, LOCK_FILE), path, flag, _belongs(root, path))
    written = written_log.clean_and_compact(root, _marker(root, LOG_FILE))
    log = os.open(_marker(root, LOG_FILE), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    claim = _Claim(root, owner_kind(root), lock, log, written)
    _claims[root] = claim
    return claim


def _release(claim: _Claim) -> None:
  with _mutex:
    claim.depth -= 1
    if claim.depth == 0:
      del _claims[claim.root]
      os.close(claim.log_descriptor)
      if claim.lock_descriptor is not None:
        os.close(claim.lock_descriptor)  # Drops the lock.


@contextlib.contextmanager
def joined(path: str | os.PathLike) -> Iterator[Path]:
  """Joins, in a child process, the claim its parent holds on `path` (while the parent waits
  for it): the child's writes are recorded in that claim's log, as the parent's are; the lock
  stays the parent's. The parent reads them back with `refresh(path)`.

  Raises:
    InputError naming `path`: it is not in a signerf directory, or this process's parent does
      not hold its lock.
  """
  root = owner_root(path)
  if root is None:
    raise InputError("is not in a directory signerf made: nothing to join", path)
  parent = os.getppid()
  if directory_lock.holder(_marker(root, LOCK_FILE)) != parent:
    raise InputError(f"is not claimed by this process's parent (pid {parent})", path)
  with _mutex:
    written, _ = written_log.read(_marker(root, LOG_FILE))
    log = os.open(_marker(root, LOG_FILE), os.O_WRONLY | os.O_APPEND)
    claim = _Claim(root, owner_kind(root), None, log, written)
    _claims[root] = claim
  try:
    yield Path(path)
  finally:
    _release(claim)


def refresh(path: str | os.PathLike) -> None:
  """Reads the files written back from the log of the claim holding `path` (a child process
  that `joined` it wrote there too); nothing outside a claim."""
  found = _claim_of(Path(path))
  if found is not None:
    with _mutex:
      found[0].written = written_log.read(_marker(found[0].root, LOG_FILE))[0]


def _active_claim(resolved: Path) -> _Claim | None:
  """This process's claim holding the resolved path, if any."""
  for candidate in (resolved, *resolved.parents):
    if candidate in _claims:
      return _claims[candidate]
  return None


def _claim_of(path: Path) -> tuple[_Claim, str] | None:
  """The claim holding `path` and its path relative to the claim's root, or None.

  Raises:
    InputError: the path is inside a claimed directory as written but leads outside it through
      a symbolic link (the project writes only inside what it claimed).
  """
  with _mutex:
    if not _claims:
      return None
    absolute = Path(os.path.abspath(path))
    resolved = absolute.parent.resolve() / absolute.name
    claim = _active_claim(resolved)
    if claim is None:
      if _active_claim(absolute) is not None:
        raise InputError("leads outside the output directory through a symbolic link; "
                         "nothing was written", path)
      return None
    return claim, resolved.relative_to(claim.root).as_posix()


def _append(claim: _Claim, record: list[str]) -> None:
  """Adds a record to the claim's log, on disk before the caller goes on."""
  written_log.append(claim.log_descriptor, record)


def check_replaceable(path: str | os.PathLike) -> None:
  """Raises unless the project may replace or delete `path`: it does not exist, it lies outside
  every claimed directory, or it is a file this project's record says it wrote.

  Raises:
    InputError naming the file.
  """
  found = _claim_of(Path(path))
  if found is None or not os.path.lexists(path):
    return
  claim, relative = found
  if relative not in claim.written:
    raise InputError("exists and was not written by signerf: it is left as it is; move it "
                     "away or choose another output directory", path)


def prepare_write(path: str | os.PathLike) -> Path:
  """The temporary file to write `path` through (`files.atomic_path`), not yet created: a hidden
  name beside `path` with its suffix. Inside a claimed directory the write is recorded first
  (so a kill leaves a temporary file the next claim removes by name) and refused when `path`
  is a file the project did not write.

  Raises:
    InputError naming the file.
  """
  path = Path(path)
  temporary = path.with_name(f".{path.stem}.{secrets.token_hex(4)}{path.suffix}")
  check_replaceable(path)
  found = _claim_of(path)
  if found is not None:
    claim, relative = found
    with _mutex:
      _append(claim, ["w", relative, str(Path(relative).with_name(temporary.name).as_posix())])
      claim.written.add(relative)
  return temporary


def record_written(path: str | os.PathLike) -> None:
  """Records a file the project made other than through `prepare_write` (a rename)."""
  found = _claim_of(Path(path))
  if found is not None:
    claim, relative = found
    with _mutex:
      _append(claim, ["w", relative])
      claim.written.add(relative)


def remove_file(path: str | os.PathLike) -> None:
  """Deletes one file the project may replace (`check_replaceable`), recording it, if it is
  there."""
  path = Path(path)
  check_replaceable(path)
  found = _claim_of(path)
  with contextlib.suppress(FileNotFoundError):
    path.unlink()
  if found is not None and found[1] in found[0].written:
    with _mutex:
      _append(found[0], ["r", found[1]])
      found[0].written.discard(found[1])


def written_files(folder: str | os.PathLike) -> list[Path]:
  """The files the project recorded at any depth under `folder` (none outside a claimed
  directory), sorted."""
  found = _claim_of(Path(folder))
  if found is None:
    return []
  claim, prefix = found
  prefix = "" if prefix == "." else prefix + "/"
  with _mutex:
    return [Path(folder) / relative[len(prefix):] for relative in sorted(claim.written)
            if relative.startswith(prefix)]


def remove_written(path: str | os.PathLike) -> int:
  """Deletes the recorded files at or under `path` (in a claimed directory), and the folders
  that held them once they are empty; everything else there stays. Returns how many files
  were deleted (0 outside a claimed directory: nothing there is known to be the project's)."""
  found = _claim_of(Path(path))
  if found is None:
    return 0
  claim, prefix = found
  prefix = "" if prefix == "." else prefix
  with _mutex:
    chosen = sorted(relative for relative in claim.written
                    if not prefix or relative == prefix or relative.startswith(prefix + "/"))
    folders = set()
    for relative in chosen:
      with contextlib.suppress(FileNotFoundError):
        (claim.root / relative).unlink()
      _append(claim, ["r", relative])
      claim.written.discard(relative)
      folders.update(parent for parent in Path(relative).parents
                     if parent.as_posix().startswith(prefix) and parent != Path("."))
  for folder in sorted(folders, key=lambda folder: len(folder.parts), reverse=True):
    with contextlib.suppress(OSError):  # Not empty: something of the user's is there.
      (claim.root / folder).rmdir()
  return len(chosen)


def clear(path: str | os.PathLike, kind: str) -> None:
  """Deletes what the project wrote in the directory `path` (claiming it), keeping anything
  else; nothing when `path` does not exist. For experiments that start a run afresh."""
  if Path(path).exists():
    with claimed(path, kind):
      remove_written(path)


def is_disk_full(error: OSError) -> bool:
  """Whether a write failed for want of space (the disk or the user's quota)."""
  return error.errno in (errno.ENOSPC, errno.EDQUOT)
