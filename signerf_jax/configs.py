"""The gin edge: flags, parsing, the library's configurable classes, building them, saving.

Library code never reads gin: its settings are plain frozen dataclasses passed as arguments.
The commands and experiments parse gin (`parse_gin`) and turn the bindings into those
dataclasses with `build`, under the gin names of `configurables()` (e.g. `TrainConfig.steps`,
`finetune/TrainConfig.steps` in scope "finetune", `synthetic_cameras.num_views`). A scoped
binding must name a scope and class some command builds (`scopes()`): any other would be ignored
without a word.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import importlib.resources
import os
from pathlib import Path
from typing import Any, Iterator, Sequence, TypeVar

import gin
from gin import config_parser

from signerf_jax import files
from signerf_jax.errors import InputError


def _gin_config_dir() -> Path:
  """The package data signerf_jax.gin_configs: pyproject.toml maps it onto the top-level
  gin_configs/ (the design card's layout). A wheel holds it in the package; an editable install or
  a checkout does not (setuptools' editable finder cannot import a folder without __init__.py):
  there the package's folder sits in the checkout, beside gin_configs/."""
  package = Path(str(importlib.resources.files("signerf_jax")))
  shipped = package / "gin_configs"
  return shipped if shipped.is_dir() else package.resolve().parent / "gin_configs"


GIN_CONFIG_DIR = _gin_config_dir()
SAVED_CONFIG_NAME = "config.gin"
Config = TypeVar("Config")
# How deep a gin value's brackets may nest. gin's parser, its evaluation and the checks recurse
# once per level (gin's parser overflows Python's stack at ~450): far deeper than any setting
# needs, far from the stack's limit.
MAX_NESTING = 100
# What gin's parser makes of `%constant` and of `@name()` for a name not registered (yet), which
# gin does not export.
# pylint: disable-next=protected-access
_GIN_CONSTANT = gin.config._retrieve_constant
# pylint: disable-next=protected-access
_GIN_UNKNOWN_REFERENCE = gin.config._UnknownConfigurableReference


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


def scopes() -> dict[str, tuple[type, ...]]:
  """Every gin scope a command builds configs in -> the classes of `configurables()` it builds
  there (e.g. "finetune" -> TrainConfig: `finetune/TrainConfig.steps`).

  A scoped binding of any other scope or class would never apply, so `parse_gin` refuses it;
  `build` refuses a scope not listed here, so the list cannot fall behind the commands.
  """
  # pylint: disable=g-import-not-at-top
  from signerf_jax.diffusion.pipeline import GenerationOptions
  from signerf_jax.editing import config as edit
  from signerf_jax.nerf.train import TrainConfig
  return {**{run: (TrainConfig,) for run in edit.TRAINING_RUNS},
          **{iteration: (GenerationOptions,) for iteration in edit.GENERATION_SCOPES}}


def _scope_names() -> str:
  """The valid scoped names, for error messages: "original/TrainConfig, ..."."""
  names = configurables()
  return ", ".join(f"{scope}/{names[cls]}" for scope, classes in scopes().items()
                   for cls in classes)


@functools.cache
def _gin_classes() -> dict[type, type]:
  """Each class of `configurables()` -> the subclass gin registered for it, which applies the
  bindings when called (the class itself stays plain). Registered once per process."""
  return {cls: gin.external_configurable(cls, name=name) for cls, name in configurables().items()}


def build(cls: type[Config], scope: str | None = None) -> Config:
  """`cls()` with the current gin bindings of its gin name applied.

  Args:
    cls: a class of `configurables()`, e.g. `train.TrainConfig`.
    scope: a gin scope to build in, one of `scopes()`, e.g. "finetune":
      `finetune/TrainConfig.*` bindings win over `TrainConfig.*` ones; None: only the scopes
      the caller has entered (usually none).
  Returns:
    an instance of `cls` itself (equal to `cls(...)` with the same values).
  Raises:
    InputError: `cls` is not one of `configurables()`, `scope` not one of `scopes()`, or the
      class's checks (`validation`) reject a bound value; the error names the binding, e.g.
      `finetune/TrainConfig.steps`.
  """
  wrapped = _gin_classes().get(cls)
  if wrapped is None:
    raise InputError(f"{getattr(cls, '__qualname__', repr(cls))} is not a class gin binds (see "
                     "configs.configurables())", field="cls")
  if scope is not None and scope not in scopes():
    # A scope parse_gin does not know would let its bindings through unchecked.
    raise InputError(f"{scope!r} is not a gin scope of configs.scopes() ({_scope_names()})",
                     field="scope")
  prefix = f"{scope}/" if scope else ""
  try:
    with gin.config_scope(scope) if scope is not None else contextlib.nullcontext():
      instance = wrapped()
  except RecursionError:
    # parse_gin refuses cycles and deep nesting; only an absurdly long chain of macros gets here.
    raise InputError("its gin bindings refer to one another too deeply to evaluate (a chain of "
                     "macros or references)", field=prefix + configurables()[cls]) from None
  except InputError as error:
    # The class's checks name `<class>.<field>`; the user wrote `<scope>/<gin name>.<field>`.
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


def read_gin_file(path: str | os.PathLike) -> str:
  """The text of a gin file; InputError naming it when it is not UTF-8 text (gin reads text)."""
  try:
    data = Path(path).read_bytes()
  except OSError as error:
    raise InputError(f"cannot be read: {error.strerror or error}", path) from None
  try:
    return data.decode("utf-8")
  except UnicodeDecodeError as error:
    line = data.count(b"\n", 0, error.start) + 1
    raise InputError(f"not UTF-8 text (byte {data[error.start]:#04x} on line {line}); gin "
                     "files are text: save it as UTF-8", path) from None


def check_gin_is_data(text: str, source: str | os.PathLike | None,
                      including: tuple[Path, ...] = ()
                      ) -> list[tuple[str | os.PathLike | None, config_parser.BindingStatement]]:
  """Refuses gin text that would run code or could never apply, before gin sees it.

  gin executes `import` (and `from ... import`) statements: any module on the path, or one
  placed beside a copied run directory, would run. Configuration here is data: bindings of
  registered configurables only (their values are literals, macros and references). Files
  named by `include` are checked the same way. A scoped binding must name a scope and class of
  `scopes()` (gin would silently ignore any other), and values may nest at most `MAX_NESTING`
  brackets deep (deeper ones overflow gin's parser and evaluation).

  Args:
    text: gin file contents or one binding.
    source: the file (or "gin_param") named in errors.
    including: files already being checked (an include cycle is an error, not a recursion).
  Returns:
    (source, statement) of every binding, included files' in place of the `include`, in the
    order gin applies them.
  Raises:
    InputError naming the file and line of the first statement that is not a binding, the
    binding of an unknown scope, or the value nested too deeply.
  """
  parser = config_parser.ConfigParser(text, gin.config.ParserDelegate(skip_unknown=True))
  try:
    statements = list(parser)
  except SyntaxError as error:
    raise InputError(f"line {error.lineno}: not gin syntax: {error.msg}", source) from None
  except RecursionError:
    # gin's parser recurses once per bracket: thousands of them overflow Python's stack.
    token = parser.current_token
    line = f"line {token.start[0]}: " if token is not None else ""
    raise InputError(f"{line}brackets nest more than {MAX_NESTING} levels deep", source) from None
  bindings = []
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
      bindings += check_gin_is_data(read_gin_file(included), included, including + (included,))
    if isinstance(statement, config_parser.BindingStatement):
      _check_binding(statement, source)
      bindings.append((source, statement))
  return bindings


def _binding_key(statement: config_parser.BindingStatement) -> str:
  """The binding as written before " = ": `finetune/TrainConfig.steps`, or a macro's name."""
  scope = f"{statement.scope}/" if statement.scope else ""
  parameter = f".{statement.arg_name}" if statement.arg_name else ""
  return f"{scope}{statement.selector}{parameter}"


def _check_binding(statement: config_parser.BindingStatement,
                   source: str | os.PathLike | None) -> None:
  """A scoped binding names a scope and class of `scopes()`; its value nests not too deeply."""
  line = f"line {statement.location.line_num}"
  if statement.scope and statement.arg_name:  # Not a macro (`scope/name = value`).
    name = statement.selector.rsplit(".", 1)[-1]
    built = [configurables()[cls] for cls in scopes().get(statement.scope, ())]
    if name not in built:
      built = (f"the commands build only {', '.join(built)} in it" if built
               else "no command builds anything in it")
      raise InputError(f"{line}: gin scope {statement.scope!r}: {built}, so this binding would "
                       f"be ignored; the scoped names are {_scope_names()}", source,
                       _binding_key(statement))
  if _nesting(statement.value) > MAX_NESTING:
    raise InputError(f"{line}: brackets nest more than {MAX_NESTING} levels deep", source,
                     _binding_key(statement))


def _nesting(value: Any, depth: int = 0) -> int:
  """How many containers deep `value` nests (stops counting past MAX_NESTING)."""
  if depth > MAX_NESTING or not isinstance(value, (list, tuple, dict)):
    return depth
  items = [*value.keys(), *value.values()] if isinstance(value, dict) else value
  return max((_nesting(item, depth + 1) for item in items), default=depth + 1)


def _references(value: Any) -> Iterator[tuple[str, str]]:
  """What evaluating a parsed gin value calls: ("macro", name) for `%name`, ("configurable",
  name) for `@name()` (an unevaluated `@name` is only passed along; constants are values)."""
  if isinstance(value, dict):
    for item in (*value.keys(), *value.values()):
      yield from _references(item)
  elif isinstance(value, (list, tuple)):
    for item in value:
      yield from _references(item)
  elif isinstance(value, gin.config.ConfigurableReference) and value.evaluate:
    if value.configurable.wrapped is gin.config.macro:
      yield "macro", "/".join(value.scopes)
    elif value.configurable.wrapped is not _GIN_CONSTANT:
      yield "configurable", value.configurable.name
  elif isinstance(value, _GIN_UNKNOWN_REFERENCE) and value.evaluate:
    yield "configurable", value.selector.rsplit(".", 1)[-1]


def _check_references(bindings) -> None:
  """Refuses macros used but never defined, and bindings that refer back to themselves (`a =
  %b` with `b = %a`, `TrainConfig.steps = @TrainConfig()`): gin would recurse until Python's
  stack overflows when the class is built.

  Args:
    bindings: (source, statement) of every binding, in the order gin applies them (a later
      binding of the same name replaces an earlier one).
  """
  final = {(statement.scope, statement.selector, statement.arg_name): (source, statement)
           for source, statement in bindings}
  defined = {_binding_key(statement) for _, statement in final.values()
             if not statement.arg_name}
  # node -> [(node it calls, the binding that makes it call it)]. A binding of a class makes
  # that class call its references whatever the binding's scope: cycles are refused even if
  # only reached in one scope.
  edges: dict[tuple[str, str], list] = {}
  for source, statement in final.values():
    node = (("macro", _binding_key(statement)) if not statement.arg_name
            else ("configurable", statement.selector.rsplit(".", 1)[-1]))
    for reference in _references(statement.value):
      if reference[0] == "macro" and reference[1] not in defined:
        raise InputError(f"line {statement.location.line_num}: %{reference[1]} is used but never "
                         f"defined (define it with `{reference[1]} = VALUE`)", source,
                         _binding_key(statement))
      edges.setdefault(node, []).append((reference, source, statement))
  # Depth-first, with an explicit stack: a long chain of macros must not overflow Python's.
  finished = set()
  for root in list(edges):
    if root in finished:
      continue
    stack = [(root, iter(edges.get(root, ())))]  # The nodes of the current descent...
    depth = {root: 0}  # ... their positions in it...
    path = []  # ... and the edge taken from each of them but the last.
    while stack:
      node, remaining = stack[-1]
      edge = next(remaining, None)
      if edge is None:
        stack.pop()
        del depth[node]
        finished.add(node)
        if path:
          path.pop()
        continue
      if edge[0] in depth:
        _refuse_cycle(path[depth[edge[0]]:] + [edge])
      if edge[0] not in finished:
        path.append(edge)
        depth[edge[0]] = len(stack)
        stack.append((edge[0], iter(edges.get(edge[0], ()))))


def _refuse_cycle(cycle) -> None:
  """InputError naming each binding of a cycle of references, blaming the first."""
  steps = " -> ".join(f"`{statement.location.line_content.strip()}` ({source or 'gin_param'}, "
                      f"line {statement.location.line_num})" for _, source, statement in cycle)
  _, source, statement = cycle[0]
  raise InputError(f"line {statement.location.line_num}: the bindings refer back to themselves, "
                   f"which gin would follow forever: {steps}", source, _binding_key(statement))


def _one_line(error: Exception) -> str:
  """gin's message on one line: its first line, with the location lines it appends joined."""
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  return "; ".join(lines[:3])


def parse_gin(gin_files: Sequence[str | os.PathLike] = (), gin_params: Sequence[str] = (),
              finalize: bool = True) -> None:
  """Clears any previous bindings, then applies files in order and parameters on top (each
  checked first: `check_gin_is_data`, and together for macros that are never defined or refer
  back to themselves). Every class of `configurables()` is registered first."""
  _gin_classes()
  gin.clear_config()
  paths = [resolve_gin_file(name) for name in gin_files]
  bindings = []
  for path in paths:
    bindings += check_gin_is_data(read_gin_file(path), path, (path.resolve(),))
  for binding in gin_params:
    bindings += check_gin_is_data(binding, "gin_param")
  _check_references(bindings)
  paths = [str(path) for path in paths]
  gin.add_config_file_search_path(str(GIN_CONFIG_DIR))
  try:
    gin.parse_config_files_and_bindings(paths, list(gin_params), finalize_config=finalize)
  except (ValueError, KeyError, SyntaxError) as error:
    raise InputError(f"bad gin configuration: {_one_line(error)}", ", ".join(paths) or None,
                     "gin_param") from None
  except RecursionError:
    raise InputError("bad gin configuration: nested or chained too deeply for gin",
                     ", ".join(paths) or None, "gin_param") from None


def save_gin_config(directory: str | os.PathLike) -> Path:
  """Writes every current binding (not only the ones used so far) to `directory`/config.gin."""
  path = Path(directory) / SAVED_CONFIG_NAME
  path.parent.mkdir(parents=True, exist_ok=True)
  files.write_text(path, gin.config_str())
  return path
