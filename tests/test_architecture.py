"""The library imports one way and reads no gin.

Edges (`is_edge`: the command line, gin's table, every command, the demo, the browser viewer,
default_model) turn
gin and flags into calls and may import anything; no other module imports an edge. The other
modules' folders import one way: each only from the folders below it in LAYERS and from the
top-level modules, which import no folder. Only edges import gin, and no function is gin-bound.
No module imports itself through a cycle. Modules and functions stay short enough to read, and
every public function at a module's top level says what it does in a docstring.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "signerf_jax"
# Lowest first. default_model (the shipped model's training and evaluation) sits beside the
# experiments, an edge: the library reaches it only through the path of its weights.
LAYERS = ("data", "metrics", "nerf", "geometry", "clip", "diffusion", "editing", "viewer",
          "default_model")
EDGE_MODULES = ("signerf_jax.cli", "signerf_jax.configs", "signerf_jax.editing.demo")
# A module owns one idea and a function does one thing (issue 16's goal: lines, docstrings in).
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 60
# The hooks every command module exposes to `signerf_jax.cli`, whose docstring defines them.
COMMAND_HOOKS = ("add_arguments", "run")


def is_edge(module: str) -> bool:
  """Whether `module` is where gin and the command line meet the library: `cli`, `configs`,
  the demo, any `commands` module or package (and what it holds), the viewer (the command line
  of the browser) and all of default_model."""
  parts = module.split(".")
  return (module in EDGE_MODULES or "commands" in parts
          or parts[1:2] in (["default_model"], ["viewer"]))


def module_name(path: Path) -> str:
  parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
  return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_level_nodes(tree: ast.AST):
  """The nodes of `tree` that run when the module is imported (not those inside functions)."""
  stack = [tree]
  while stack:
    node = stack.pop()
    yield node
    stack.extend(child for child in ast.iter_child_nodes(node) if not isinstance(
        child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))


def imported_modules(source: str, package: str, module_level_only: bool = False) -> set[str]:
  """signerf_jax modules `source` (a module of `package`) imports anywhere (function-level
  imports included unless `module_level_only`); `from package import name` counts as
  `package.name` when that is a module."""
  found = set()
  tree = ast.parse(source)
  for node in module_level_nodes(tree) if module_level_only else ast.walk(tree):
    if isinstance(node, ast.Import):
      found.update(alias.name for alias in node.names)
    elif isinstance(node, ast.ImportFrom):
      base = node.module or ""
      if node.level:
        anchor = package.split(".")[:len(package.split(".")) - node.level + 1]
        base = ".".join(anchor + ([node.module] if node.module else []))
      found.add(base)
      found.update(f"{base}.{alias.name}" for alias in node.names)
  return {name for name in found if name.split(".")[0] == "signerf_jax" and module_exists(name)}


def module_exists(name: str) -> bool:
  path = PACKAGE.parent.joinpath(*name.split("."))
  return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def layer(module: str) -> int:
  """Index in LAYERS of the module's folder; -1 for the package's top-level modules."""
  parts = module.split(".")
  if len(parts) < 2 or parts[1] not in LAYERS:
    if len(parts) >= 2 and (PACKAGE / parts[1]).is_dir():
      raise AssertionError(f"folder signerf_jax/{parts[1]} is missing from LAYERS")
    return -1
  return LAYERS.index(parts[1])


def sources() -> dict[str, str]:
  """module name -> its source, for every module of the package."""
  return {module_name(path): path.read_text() for path in sorted(PACKAGE.rglob("*.py"))}


def import_graph(module_level_only: bool = False) -> dict[str, set[str]]:
  """module -> the signerf_jax modules it imports."""
  graph = {}
  for name, source in sources().items():
    is_package = (PACKAGE.parent.joinpath(*name.split(".")) / "__init__.py").is_file()
    package = name if is_package else name.rpartition(".")[0]
    graph[name] = imported_modules(source, package, module_level_only)
  return graph


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
  """Imports that break the rules of non-edge modules: of an edge, or of a higher folder (a
  top-level module, layer -1, imports no folder)."""
  return [f"{module} imports {target}" for module, targets in graph.items() for target in targets
          if not is_edge(module) and (is_edge(target) or layer(target) > layer(module))]


def test_layers_name_every_folder():
  folders = {path.name for path in PACKAGE.iterdir()
             if path.is_dir() and (path / "__init__.py").is_file()}
  assert folders == set(LAYERS)


def test_no_folder_imports_a_folder_above_it_and_only_edges_import_edges():
  upward = upward_imports(import_graph())
  assert not upward, "\n".join(upward)


def test_upward_and_relative_imports_are_found():
  source = ("from signerf_jax.editing import sheet\nfrom . import dataset\n"
            "def lazy():\n  import signerf_jax.diffusion.unet\n")
  imported = imported_modules(source, "signerf_jax.data")
  assert {"signerf_jax.editing.sheet", "signerf_jax.data.dataset",
          "signerf_jax.diffusion.unet"} <= imported
  assert set(upward_imports({"signerf_jax.data.probe": imported})) == {
      f"signerf_jax.data.probe imports signerf_jax.{name}"
      for name in ("editing", "editing.sheet", "diffusion.unet")}
  assert upward_imports({"signerf_jax.files": {"signerf_jax.nerf.model"}})
  assert not upward_imports({"signerf_jax.editing.sheet": {"signerf_jax.nerf.model"}})
  # Edges import anything; nothing else imports an edge, even one in a lower folder.
  assert not upward_imports({"signerf_jax.configs": {"signerf_jax.editing.demo"},
                             "signerf_jax.nerf.commands.train": {"signerf_jax.configs"},
                             "signerf_jax.default_model.samples": {"signerf_jax.editing.crops"}})
  assert upward_imports({"signerf_jax.errors": {"signerf_jax.configs"}})
  assert upward_imports({"signerf_jax.editing.stages.runner": {"signerf_jax.nerf.commands"}})
  assert upward_imports({"signerf_jax.editing.sheet": {"signerf_jax.editing.demo"}})
  lazy = imported_modules("import signerf_jax.files\ndef f():\n  import signerf_jax.math\n",
                          "signerf_jax", module_level_only=True)
  assert lazy == {"signerf_jax.files"}


@pytest.mark.parametrize("module, edge", [
    ("signerf_jax.cli", True), ("signerf_jax.configs", True), ("signerf_jax.editing.demo", True),
    ("signerf_jax.data.commands.synthesize", True), ("signerf_jax.data.commands.process", True),
    ("signerf_jax.nerf.commands", True),
    ("signerf_jax.editing.commands.sweeps", True), ("signerf_jax.default_model.samples", True),
    ("signerf_jax.files", False), ("signerf_jax.nerf.train", False),
    ("signerf_jax.editing.config", False)])
def test_edges_are_the_command_line_gin_and_default_model(module, edge):
  assert is_edge(module) == edge


def gin_names(tree: ast.AST) -> dict[str, str]:
  """Local name -> what it names in gin, for `import gin [as g]` and `from gin import x [as y]`."""
  names = {}
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      names.update({alias.asname or alias.name: alias.name for alias in node.names
                    if alias.name.split(".")[0] == "gin"})
    elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "gin":
      names.update({alias.asname or alias.name: f"{node.module}.{alias.name}"
                    for alias in node.names})
  return names


def gin_bound_functions(source: str) -> list[str]:
  """Functions `source` decorates with gin.configurable or gin.register (which make a function
  read gin bindings whenever it is called)."""
  tree = ast.parse(source)
  names = gin_names(tree)
  found = []
  for node in ast.walk(tree):
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
      for decorator in node.decorator_list:
        target = ast.unparse(decorator.func if isinstance(decorator, ast.Call) else decorator)
        head, _, rest = target.partition(".")
        if ".".join(filter(None, [names.get(head, head), rest])) in ("gin.configurable",
                                                                   "gin.register"):
          found.append(node.name)
  return found


def test_only_edges_import_gin():
  importing = [module for module, source in sources().items()
               if not is_edge(module) and gin_names(ast.parse(source))]
  assert not importing, importing


def test_no_function_is_gin_bound():
  bound = {module: names for module, source in sources().items()
           if (names := gin_bound_functions(source))}
  assert not bound, bound


def test_gin_imports_and_gin_bound_functions_are_found():
  source = ("import gin as g\nfrom gin import configurable\n@g.configurable\ndef a(x=1): ...\n"
            "@configurable('b')\ndef b(x=1): ...\n@gin.register\ndef c(): ...\n"
            "@dataclasses.dataclass\nclass D: ...\n@functools.cache\ndef e(): ...\n")
  assert set(gin_names(ast.parse(source))) == {"g", "configurable"}
  assert gin_bound_functions(source) == ["a", "b", "c"]


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
  """A list of modules each importing the next and the last the first, or None."""
  state: dict[str, str] = {}
  stack: list[str] = []

  def visit(module: str) -> list[str] | None:
    state[module] = "open"
    stack.append(module)
    for target in sorted(graph.get(module, ())):
      if state.get(target) == "open":
        return stack[stack.index(target):]
      if target not in state and (cycle := visit(target)):
        return cycle
    stack.pop()
    state[module] = "done"
    return None

  for module in sorted(graph):
    if module not in state and (cycle := visit(module)):
      return cycle
  return None


def cycle_edges(graph: dict[str, set[str]]) -> dict[str, set[str]]:
  """The imports that can close a cycle. A package's __init__ importing its own modules is how
  packages expose names, and a module importing its own package (`from signerf_jax.x import
  y`) goes through that __init__: only imports between different modules that are not
  package-to-own-package count."""
  return {module: {target for target in targets
                   if target != module and not module.startswith(target + ".")}
          for module, targets in graph.items()}


def test_no_import_cycle():
  # Among the library's modules none at all; edges may import anything when called (configs
  # imports the classes it registers, editing.demo's among them, when first used), but a cycle
  # of imports run at import time would leave a module half-initialised.
  library = {module: {target for target in targets if not is_edge(target)}
             for module, targets in cycle_edges(import_graph()).items() if not is_edge(module)}
  assert find_cycle(library) is None, " -> ".join(find_cycle(library))
  at_import = cycle_edges(import_graph(module_level_only=True))
  assert find_cycle(at_import) is None, " -> ".join(find_cycle(at_import))


@pytest.mark.parametrize("graph, cycle", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c"]),
    ({"a": {"a"}}, ["a"]),
])
def test_find_cycle(graph, cycle):
  assert find_cycle(graph) == cycle


def long_functions(source: str, limit: int) -> list[str]:
  """`name (lines)` of the functions and methods of `source` longer than `limit` lines."""
  return [f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
          for node in ast.walk(ast.parse(source))
          if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
          and node.end_lineno - node.lineno + 1 > limit]


def test_modules_and_functions_are_short():
  long_modules = {name: len(source.splitlines()) for name, source in sources().items()
                  if len(source.splitlines()) > MAX_MODULE_LINES}
  assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
  functions = {name: found for name, source in sources().items()
               if (found := long_functions(source, MAX_FUNCTION_LINES))}
  assert not functions, f"functions over {MAX_FUNCTION_LINES} lines: {functions}"


def test_long_functions_are_found():
  source = "def short():\n  return 1\n\nclass A:\n  def long(self):\n" + "    x = 1\n" * 3
  assert long_functions(source, 3) == ["long (4 lines)"]
  assert long_functions(source, 4) == []


def undocumented_functions(source: str) -> list[str]:
  """Public top-level functions of `source` without a docstring (command hooks excepted)."""
  return [node.name for node in ast.parse(source).body
          if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
          and not node.name.startswith("_") and node.name not in COMMAND_HOOKS
          and ast.get_docstring(node) is None]


def test_public_functions_have_docstrings():
  undocumented = {name: found for name, source in sources().items()
                  if (found := undocumented_functions(source))}
  assert not undocumented, f"public functions without a docstring: {undocumented}"


def test_undocumented_functions_are_found():
  source = ('def bare():\n  return 1\n\ndef told():\n  """Says."""\n\ndef _private():\n  pass\n'
            "\ndef run(args):\n  pass\n\nclass A:\n  def method(self):\n    pass\n")
  assert undocumented_functions(source) == ["bare"]
