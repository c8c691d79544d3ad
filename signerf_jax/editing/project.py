"""The edit directory: where every stage writes, which stages are finished, and provenance.

Layout (iteration 2, when enabled, repeats the iteration folders under `iteration_2/`):
  config.gin            every gin binding of the edit (the edit is reproducible from it)
  stages.json           per finished stage: its key, wall seconds, one-line summary
  original/             the original NeRF run (unless `EditConfig.original_run` names one)
  selection/            selection.json, proxy.ply (the placed proxy, scene frame)
  views/                per dataset view: frame_NNNNN.npz (mask, control, control depth)
  reference/            cameras.json, inputs.npz (the tiles) and tiles.png
  preview/              candidates/<recipe>.npz|png, preview.png (the candidates side by side)
  sheet/                sheet.npz (rgb, control, mask of the chosen sheet), sheet.png
  update/               images/frame_NNNNN.png (edited views), tiles/ (their generated slots)
  dataset/              the edited dataset in nerfstudio format
  edited/               the edited NeRF run
  evaluation/           metrics.json, before_after.png, sheet.png, video

Resumability: a stage is finished when stages.json holds its record and the record's key (the
settings the stage depends on) equals the current one; a changed key redoes that stage and every
later one. Long stages write one file per view atomically, so an interrupted stage resumes where
it stopped.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
import zipfile
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError

STAGES_FILE = "stages.json"
FRAME_NAME = "frame_{:05d}"


def frame_name(index: int) -> str:
  """The file stem of dataset view `index` (frame_00042 for 42)."""
  return FRAME_NAME.format(index)


def canonical_json(value: Any) -> str:
  """One JSON text per value (sorted keys; arrays as lists, anything else by its str)."""
  return json.dumps(value, sort_keys=True, default=_plain)


def _plain(value: Any) -> Any:
  if isinstance(value, (np.ndarray, np.generic)):
    return value.tolist()
  return str(value)


@dataclasses.dataclass(frozen=True)
class StageRecord:
  """A finished stage: the settings it ran with, its wall time and summary line."""

  key: Any
  seconds: float
  summary: str


class EditDirectory:
  """Paths of one edit directory and its stage records."""

  def __init__(self, root: str | os.PathLike):
    self.root = Path(root)

  def iteration(self, iteration: int) -> Path:
    """The folder holding an iteration's reference, sheet, update, dataset and edited NeRF."""
    return self.root if iteration == 1 else self.root / f"iteration_{iteration}"

  def path(self, *parts: str, iteration: int = 1) -> Path:
    return self.iteration(iteration).joinpath(*parts)

  # Stage records.

  def _records(self) -> dict[str, dict[str, Any]]:
    path = self.root / STAGES_FILE
    if not path.is_file():
      return {}
    return files.read_json(path)

  def record(self, stage: str) -> StageRecord | None:
    entry = self._records().get(stage)
    return None if entry is None else StageRecord(entry["key"], entry["seconds"], entry["summary"])

  def is_finished(self, stage: str, key: Any) -> bool:
    record = self.record(stage)
    return record is not None and canonical_json(record.key) == canonical_json(key)

  def finish(self, stage: str, key: Any, seconds: float, summary: str) -> None:
    records = self._records()
    records[stage] = {"key": json.loads(canonical_json(key)), "seconds": seconds,
                      "summary": summary, "finished_at": time.strftime("%Y-%m-%d %H:%M:%S")}
    files.write_json(self.root / STAGES_FILE, records)

  def forget(self, stages) -> None:
    """Drops the records of `stages` (they will run again)."""
    records = self._records()
    if any(stage in records for stage in stages):
      files.write_json(self.root / STAGES_FILE, {name: entry for name, entry in records.items()
                                                 if name not in stages})

  def stage_seconds(self) -> dict[str, float]:
    return {name: entry["seconds"] for name, entry in self._records().items()}


def save_arrays(path: str | os.PathLike, **arrays: np.ndarray) -> None:
  """Writes a .npz atomically (uncompressed: the arrays are read back whole)."""
  with files.atomic_path(path) as temporary:
    with open(temporary, "wb") as handle:
      np.savez(handle, **arrays)


def load_arrays(path: str | os.PathLike, required: Sequence[str] = ()) -> dict[str, np.ndarray]:
  """The arrays of a stage's .npz output.

  Raises:
    InputError naming the file: missing, unreadable (truncated, not a .npz, pickled objects) or
      without one of the `required` arrays.
  """
  path = Path(path)
  if not path.is_file():
    raise InputError("stage output not found (run the earlier stages first)", path)
  try:
    with np.load(path, allow_pickle=False) as data:
      arrays = {name: data[name] for name in data.files}
  except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
    raise InputError(f"damaged stage output ({type(error).__name__}: {error}); run its stage "
                     "again (--redo STAGE)", path) from None
  missing = [name for name in required if name not in arrays]
  if missing:
    raise InputError(f"damaged stage output: no {missing} arrays; run its stage again "
                     "(--redo STAGE)", path)
  return arrays


def directory_fingerprint(directory: str | os.PathLike) -> dict[str, Any]:
  """sha256 over every file of a directory (relative path and contents), for provenance."""
  directory = Path(directory)
  digest = hashlib.sha256()
  count, size = 0, 0
  for path in sorted(p for p in directory.rglob("*") if p.is_file()
                     and not any(part.startswith(".") for part in p.relative_to(directory).parts)):
    digest.update(path.relative_to(directory).as_posix().encode("utf-8") + b"\0")
    with open(path, "rb") as handle:
      for block in iter(lambda: handle.read(1 << 22), b""):
        digest.update(block)
    count += 1
    size += path.stat().st_size
  return {"path": str(directory.resolve()), "sha256": digest.hexdigest(), "files": count,
          "bytes": size}
