"""Checkpoints of every trainer (the NeRF, its fine-tuning, the shipped model's stages): the whole
training state (a flax-serialisable pytree) and JSON-like metadata in one msgpack file.

The file holds the serialised payload and its sha256, so a damaged or altered checkpoint is
never a silently different resume, and it is replaced atomically (written to a temporary file,
flushed to disk, renamed), so an interrupted run keeps the previous one. The checkpoint it
replaces is kept as checkpoint.previous.msgpack: when the latest is damaged (or a kill left only
the previous one), `read` falls back to it with a warning. Temporary files a killed run left
behind are removed when the run directory is next claimed (`ownership`).
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path
from typing import Any, Callable, TypeVar

import flax.serialization
import jax
import numpy as np

from signerf_jax import distributed, files, ownership
from signerf_jax.errors import InputError

CHECKPOINT_NAME = "checkpoint.msgpack"
PREVIOUS_NAME = "checkpoint.previous.msgpack"

State = TypeVar("State")


def checkpoint_path(directory: str | os.PathLike) -> Path:
  """The latest checkpoint's file in a run's `directory`."""
  return Path(directory) / CHECKPOINT_NAME


def has_checkpoint(directory: str | os.PathLike) -> bool:
  """Whether `directory` holds a checkpoint to resume from (the latest or the previous one)."""
  return checkpoint_path(directory).is_file() or (Path(directory) / PREVIOUS_NAME).is_file()


def save(directory: str | os.PathLike, state: Any, metadata: dict[str, Any]) -> Path:
  """Writes `state` and `metadata` to `directory`/checkpoint.msgpack atomically."""
  path = checkpoint_path(directory)
  previous = path.parent / PREVIOUS_NAME
  ownership.check_replaceable(previous)
  payload = flax.serialization.msgpack_serialize({
      "state": flax.serialization.to_state_dict(distributed.to_host(state)),
      "metadata": metadata})
  envelope = flax.serialization.msgpack_serialize(
      {"sha256": hashlib.sha256(payload).hexdigest(), "payload": payload})
  with files.atomic_path(path) as temporary:
    temporary.write_bytes(envelope)
    # Written in full before the latest becomes the previous: a kill between the two renames
    # leaves the previous checkpoint, which `read` resumes from.
    if path.is_file():
      os.replace(path, previous)
      ownership.record_written(previous)
  return path


def read(directory: str | os.PathLike) -> tuple[dict[str, Any], dict[str, Any]]:
  """The checkpoint's state (as a nested dict of arrays) and metadata, checksum verified. A
  missing or damaged latest checkpoint falls back to the previous one, with a warning.

  Raises:
    InputError: no checkpoint, or an unreadable one (truncated, not a checkpoint, a checksum
      that does not match its contents) and no readable previous one.
  """
  path, previous = checkpoint_path(directory), Path(directory) / PREVIOUS_NAME
  try:
    return _read_file(path)
  except InputError as error:
    if not previous.is_file():
      raise
    try:
      state, metadata = _read_file(previous)
    except InputError:
      raise error from None
    warnings.warn(f"{error}; resuming from the previous checkpoint {previous} (step "
                  f"{metadata.get('step', '?')})", stacklevel=2)
    return state, metadata


def _read_file(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
  if not path.is_file():
    raise InputError("checkpoint not found", path)
  try:
    envelope = flax.serialization.msgpack_restore(path.read_bytes())
    payload, digest = envelope["payload"], envelope["sha256"]
    matches = hashlib.sha256(payload).hexdigest() == digest
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"not a readable checkpoint (truncated or another format: {error})",
                     path) from None
  if not matches:
    raise InputError("the checkpoint is damaged: its contents do not match their checksum",
                     path, "sha256")
  contents = flax.serialization.msgpack_restore(payload)
  return contents["state"], contents.get("metadata", {})


def restore(directory: str | os.PathLike, template: State,
            upgrade: Callable[[dict[str, Any]], dict[str, Any]] | None = None
            ) -> tuple[State, dict[str, Any]]:
  """Reads a checkpoint into the structure of `template` (shapes must match).

  Args:
    upgrade: maps the checkpoint's state dict to the current layout (what an older version
      of the trainer wrote), or None.
  Returns:
    (state, metadata).
  """
  state_dict, metadata = read(directory)
  path = checkpoint_path(directory)
  try:
    state = flax.serialization.from_state_dict(
        template, state_dict if upgrade is None else upgrade(state_dict))
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"checkpoint does not match this model ({error})", path, "state") from None
  template_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(template)]
  restored_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(state)]
  if template_shapes != restored_shapes:
    raise InputError("checkpoint array shapes do not match this model", path, "state")
  return state, metadata
