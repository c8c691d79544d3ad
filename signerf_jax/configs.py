"""gin plumbing shared by every command and experiment: parse, locate, save."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import gin

from signerf_jax import files
from signerf_jax.errors import InputError

# gin_configs/ sits next to the package in the repository (the design card fixes the layout).
GIN_CONFIG_DIR = Path(__file__).resolve().parent.parent / "gin_configs"
SAVED_CONFIG_NAME = "config.gin"


def resolve_gin_file(name: str | os.PathLike) -> Path:
  """A gin file given as a path, or as a name inside gin_configs/ (".gin" optional)."""
  candidates = [Path(name), GIN_CONFIG_DIR / name, GIN_CONFIG_DIR / f"{name}.gin"]
  for candidate in candidates:
    if candidate.is_file():
      return candidate
  raise InputError(f"gin file not found (also looked in {GIN_CONFIG_DIR})", name)


def parse_gin(gin_files: Sequence[str | os.PathLike] = (), gin_params: Sequence[str] = (),
              finalize: bool = True) -> None:
  """Clears any previous bindings, then applies files in order and parameters on top."""
  gin.clear_config()
  paths = [str(resolve_gin_file(name)) for name in gin_files]
  gin.add_config_file_search_path(str(GIN_CONFIG_DIR))
  try:
    gin.parse_config_files_and_bindings(paths, list(gin_params), finalize_config=finalize)
  except (ValueError, KeyError, SyntaxError) as error:
    raise InputError(f"bad gin configuration: {error}", ", ".join(paths) or None,
                     "gin_param") from None


def save_gin_config(directory: str | os.PathLike) -> Path:
  """Writes every current binding (not only the ones used so far) to `directory`/config.gin."""
  path = Path(directory) / SAVED_CONFIG_NAME
  files.write_text(path, gin.config_str())
  return path
