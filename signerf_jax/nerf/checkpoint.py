"""Checkpoints: the whole training state (params, optimizer moments, occupancy grid, PRNG key,
step) in one msgpack file, replaced atomically so an interrupted run keeps the previous one."""

from __future__ import annotations

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


def checkpoint_path(run_dir: str | os.PathLike) -> Path:
  return Path(run_dir) / CHECKPOINT_NAME


def has_checkpoint(run_dir: str | os.PathLike) -> bool:
  return checkpoint_path(run_dir).is_file()


def save(run_dir: str | os.PathLike, state: Any, metadata: dict[str, Any]) -> Path:
  """Writes `state` (any flax-serialisable pytree) and JSON-like `metadata` atomically."""
  state_dict = flax.serialization.to_state_dict(jax.device_get(state))
  payload = flax.serialization.msgpack_serialize({"state": state_dict, "metadata": metadata})
  path = checkpoint_path(run_dir)
  files.write_bytes(path, payload)
  return path


def restore(run_dir: str | os.PathLike, template: State) -> tuple[State, dict[str, Any]]:
  """Reads a checkpoint into the structure of `template` (shapes must match).

  Returns:
    (state, metadata).
  """
  path = checkpoint_path(run_dir)
  if not path.is_file():
    raise InputError("checkpoint not found", path)
  try:
    payload = flax.serialization.msgpack_restore(path.read_bytes())
    state = flax.serialization.from_state_dict(template, payload["state"])
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"checkpoint does not match this model ({error})", path, "state") from None
  template_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(template)]
  restored_shapes = [np.shape(leaf) for leaf in jax.tree.leaves(state)]
  if template_shapes != restored_shapes:
    raise InputError("checkpoint array shapes do not match this model", path, "state")
  return state, payload.get("metadata", {})
