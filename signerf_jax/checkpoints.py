"""Checkpoints of every trainer (the NeRF, its fine-tuning, the shipped model's stages): the whole
training state (a flax-serialisable pytree) and JSON-like metadata in one msgpack file.

The file holds the serialised payload and its sha256, so a damaged or altered checkpoint is an
error rather than a silently different resume, and it is replaced atomically (written to a
temporary file, flushed to disk, renamed), so an interrupted run keeps the previous one.
Temporary files a killed run left behind are removed by the next save.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path
from typing import Any, TypeVar

import flax.serialization
import jax
import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError

CHECKPOINT_NAME = "checkpoint.msgpack"

State = TypeVar("State")


def checkpoint_path(directory: str | os.PathLike) -> Path:
  return Path(directory) / CHECKPOINT_NAME


def has_checkpoint(directory: str | os.PathLike) -> bool:
  return checkpoint_path(directory).is_file()


def save(directory: str | os.PathLike, state: Any, metadata: dict[str, Any]) -> Path:
  """Writes `state` and `metadata` to `directory`/checkpoint.msgpack atomically."""
  path = checkpoint_path(directory)
  for orphan in path.parent.glob(f".{path.stem}.*{path.suffix}"):  # `files.atomic_path` names.
    with contextlib.suppress(FileNotFoundError):
      orphan.unlink()
  payload = flax.serialization.msgpack_serialize({
      "state": flax.serialization.to_state_dict(jax.device_get(state)), "metadata": metadata})
  files.write_bytes(path, flax.serialization.msgpack_serialize(
      {"sha256": hashlib.sha256(payload).hexdigest(), "payload": payload}))
  return path


def read(directory: str | os.PathLike) -> tuple[dict[str, Any], dict[str, Any]]:
  """The checkpoint's state (as a nested dict of arrays) and metadata, checksum verified.

  Raises:
    InputError: no checkpoint, an unreadable one (truncated, not a checkpoint), or one whose
      checksum does not match its contents.
  """
  path = checkpoint_path(directory)
  if not path.is_file():
    raise InputError("checkpoint not found", path)
  try:
    envelope = flax.serialization.msgpack_restore(path.read_bytes())
    payload, digest = envelope["payload"], envelope["sha256"]
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"not a readable checkpoint (truncated or another format: {error})",
                     path) from None
  if hashlib.sha256(payload).hexdigest() != digest:
    raise InputError("the checkpoint is damaged: its contents do not match their checksum",
                     path, "sha256")
  contents = flax.serialization.msgpack_restore(payload)
  return contents["state"], contents.get("metadata", {})


def restore(directory: str | os.PathLike, template: State) -> tuple[State, dict[str, Any]]:
  """Reads a checkpoint into the structure of `template` (shapes must match).

  Returns:
    (state, metadata).
  """
  state_dict, metadata = read(directory)
  path = checkpoint_path(directory)
  try:
    state = flax.serialization.from_state_dict(template, state_dict)
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"checkpoint does not match this model ({error})", path, "state") from None
  template_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(template)]
  restored_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(state)]
  if template_shapes != restored_shapes:
    raise InputError("checkpoint array shapes do not match this model", path, "state")
  return state, metadata
