"""The gin edge: flags, parsing, the library's configurable classes, building them, saving.

Library code never reads gin: its settings are plain frozen dataclasses passed as arguments.
The commands and experiments parse gin (`parse_gin`) and turn the bindings into those
dataclasses with `build`, under the gin names of `configurables()` (e.g. `TrainConfig.steps`,
`finetune/TrainConfig.steps` in scope "finetune", `synthetic_cameras.num_views`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
from pathlib import Path
from typing import Sequence, TypeVar

import gin
from gin import config_parser

from signerf_jax import files
from signerf_jax.errors import InputError

# gin_configs/ sits next to the package in the repository (the design card fixes the layout).
GIN_CONFIG_DIR = Path(__file__).resolve().parent.parent / "gin_configs"
SAVED_CONFIG_NAME = "config.gin"
Config = TypeVar("Config")


def configurables() -> dict[type, str]:
  """Every config dataclass gin may bind -> its gin name (`<name>.<field> = value`).

  Imported when first needed rather than at the top: some classes live in edges that import
  this module (`demo` in editing.demo), which would find it half-initialised.
  """
  # pylint: disable=g-import-not-at-top
  from signerf_jax.data.synthetic import SceneSettings
  from signerf_jax.data.synthetic_render import CameraRig
  from signerf_jax.diffusion.attention import AttentionOptions
  from signerf_jax.diffusion.pipeline import GenerationOptions
  from signerf_jax.editing import config as edit
  from signerf_jax.editing.demo import DemoSettings
  from signerf_jax.geometry.reference_cameras import ReferencePlacement
  from signerf_jax.metrics.consistency import ConsistencySettings
  from signerf_jax.nerf.capacity import CapacityRules
  from signerf_jax.nerf.commands import DataConfig
  from signerf_jax.nerf.train import TrainConfig
  return {
      TrainConfig: "TrainConfig",
      CapacityRules: "CapacityRules",
      DataConfig: "DataConfig",
      SceneSettings: "synthetic_scene",
      CameraRig: "synthetic_cameras",
      ConsistencySettings: "consistency",
      ReferencePlacement: "ReferencePlacement",
      AttentionOptions: "AttentionOptions",
      GenerationOptions: "GenerationOptions",
      edit.EditConfig: "EditConfig",
      edit.SelectionConfig: "SelectionConfig",
      edit.SheetConfig: "SheetConfig",
      edit.PreviewConfig: "PreviewConfig",
      edit.UpdateConfig: "UpdateConfig",
      edit.FinetuneConfig: "FinetuneConfig",
      edit.EvaluationConfig: "EvaluationConfig",
      edit.NerfConsistencySettings: "NerfConsistencySettings",
      DemoSettings: "demo",
  }


@functools.cache
def _gin_classes() -> dict[type, type]:
  """Each class of `configurables()` -> the subclass gin registered for it, which applies the
  bindings when called (the class itself stays plain). Registered once per process."""
  return {cls: gin.external_configurable(cls, name=name) for cls, name in configurables().items()}


def build(cls: type[Config], scope: str | None = None) -> Config:
  """`cls()` with the current gin bindings of its gin name applied.

  Args:
    cls: a class of `configurables()`, e.g. `train.TrainConfig`.
    scope: a gin scope to build in, e.g. "finetune": `finetune/TrainConfig.*` bindings win
      over `TrainConfig.*` ones; None: only the scopes the caller has entered (usually none).
  Returns:
    an instance of `cls` itself (equal to `cls(...)` with the same values).
  Raises:
    InputError: `cls` is not one of `configurables()`, or its checks (`validation`) reject a
      bound value; the error names the binding, e.g. `finetune/TrainConfig.steps`.
  """
  wrapped = _gin_classes().get(cls)
  if wrapped is None:
    raise InputError(f"{getattr(cls, '__qualname__', repr(cls))} is not a class gin binds (see "
                     "configs.configurables())", field="cls")
  try:
    with gin.config_scope(scope) if scope is not None else contextlib.nullcontext():
      instance = wrapped()
  except InputError as error:
    # The class's checks name `<class>.<field>`; the user wrote `<scope>/<gin name>.<field>`.
    prefix = f"{scope}/" if scope else ""
    field = error.field or ""
    if field.split(".")[0] == cls.__name__:
      field = prefix + configurables()[cls] + field[len(cls.__name__):]
    raise InputError(error.problem, error.path, field or None) from None
  # Dataclasses compare classes too: an instance of gin's subclass never equals a plain one.
  return cls(**{field.name: getattr(instance, field.name)
                for field in dataclasses.fields(cls) if field.init})


def add_gin_arguments(parser: argparse.ArgumentParser,
                      example_binding: str = "TrainConfig.steps = 2000") -> None:
  """--gin_file and --gin_param (repeatable; files are parsed first, in order, then bindings)."""
  parser.add_argument("--gin_file", action="append", default=[],
                      help="gin file (a path or a name in gin_configs/); repeatable")
  parser.add_argument("--gin_param", action="append", default=[],
                      help=f"gin binding such as '{example_binding}'; repeatable")


def resolve_gin_file(name: str | os.PathLike) -> Path:
  """A gin file given as a path, or as a name inside gin_configs/ (".gin" optional)."""
  candidates = [Path(name), GIN_CONFIG_DIR / name, GIN_CONFIG_DIR / f"{name}.gin"]
  for candidate in candidates:
    if candidate.is_file():
      return candidate
  raise InputError(f"gin file not found (also looked in {GIN_CONFIG_DIR})", name)


def check_gin_is_data(text: str, source: str | os.PathLike | None,
                      including: tuple[Path, ...] = ()) -> None:
  """Refuses gin text that would run code, before gin sees it.

  gin executes `import` (and `from ... import`) statements: any module on the path, or one
  placed beside a copied run directory, would run. Configuration here is data: bindings of
  registered configurables only (their values are literals, macros and references). Files
  named by `include` are checked the same way.

  Args:
    text: gin file contents or one binding.
    source: the file (or "gin_param") named in errors.
    including: files already being checked (an include cycle is an error, not a recursion).
  Raises:
    InputError naming the file and line of the first statement that is not a binding.
  """
  try:
    statements = list(config_parser.ConfigParser(text, gin.config.ParserDelegate(
        skip_unknown=True)))
  except SyntaxError as error:
    raise InputError(f"line {error.lineno}: not gin syntax: {error.msg}", source) from None
  for statement in statements:
    line = f"line {statement.location.line_num}"
    if isinstance(statement, config_parser.ImportStatement):
      raise InputError(f"{line}: `{statement.location.line_content.strip()}` would run code; "
                       "gin files here may only bind parameters of signerf_jax", source,
                       "import")
    if isinstance(statement, config_parser.IncludeStatement):
      included = resolve_gin_file(statement.filename).resolve()
      if included in including:
        raise InputError(f"{line}: `include` cycle through {included}", source, "include")
      check_gin_is_data(included.read_text(), included, including + (included,))


def parse_gin(gin_files: Sequence[str | os.PathLike] = (), gin_params: Sequence[str] = (),
              finalize: bool = True) -> None:
  """Clears any previous bindings, then applies files in order and parameters on top (each
  checked first: `check_gin_is_data`). Every class of `configurables()` is registered first."""
  _gin_classes()
  gin.clear_config()
  paths = [resolve_gin_file(name) for name in gin_files]
  for path in paths:
    check_gin_is_data(path.read_text(), path, (path.resolve(),))
  for binding in gin_params:
    check_gin_is_data(binding, "gin_param")
  paths = [str(path) for path in paths]
  gin.add_config_file_search_path(str(GIN_CONFIG_DIR))
  try:
    gin.parse_config_files_and_bindings(paths, list(gin_params), finalize_config=finalize)
  except (ValueError, KeyError, SyntaxError) as error:
    raise InputError(f"bad gin configuration: {error}", ", ".join(paths) or None,
                     "gin_param") from None


def save_gin_config(directory: str | os.PathLike) -> Path:
  """Writes every current binding (not only the ones used so far) to `directory`/config.gin."""
  path = Path(directory) / SAVED_CONFIG_NAME
  path.parent.mkdir(parents=True, exist_ok=True)
  files.write_text(path, gin.config_str())
  return path
