"""The library's folders import one way: each only from the folders below it in LAYERS (and the
top-level modules, which import no folder); no module imports itself through a cycle."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "signerf_jax"
# Lowest first. default_model (the shipped model's training and evaluation) sits beside the
# experiments: the library reaches it only through the path of its weights.
LAYERS = ("data", "metrics", "nerf", "geometry", "clip", "diffusion", "editing", "default_model")


def module_name(path: Path) -> str:
  parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
  return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, package: str) -> set[str]:
  """signerf_jax modules `source` (a module of `package`) imports anywhere, function-level
  imports included; `from package import name` counts as `package.name` when that is a module."""
  found = set()
  for node in ast.walk(ast.parse(source)):
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


def import_graph() -> dict[str, set[str]]:
  """module -> the signerf_jax modules it imports."""
  graph = {}
  for path in sorted(PACKAGE.rglob("*.py")):
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    graph[name] = imported_modules(path.read_text(), package)
  return graph


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
  return [f"{module} imports {target}" for module, targets in graph.items() for target in targets
          if layer(target) > layer(module) or (layer(module) == -1 and layer(target) != -1)]


def test_layers_name_every_folder():
  folders = {path.name for path in PACKAGE.iterdir()
             if path.is_dir() and (path / "__init__.py").is_file()}
  assert folders == set(LAYERS)


def test_no_folder_imports_a_folder_above_it():
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


def test_no_import_cycle():
  graph = import_graph()
  # A package's __init__ importing its own modules is how packages expose names, and a module
  # importing its own package (`from signerf_jax.x import y`) goes through that __init__: only
  # edges between different modules that are not package-to-own-package count.
  edges = {module: {target for target in targets
                    if target != module and not module.startswith(target + ".")}
           for module, targets in graph.items()}
  assert find_cycle(edges) is None, " -> ".join(find_cycle(edges))


@pytest.mark.parametrize("graph, cycle", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, None),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}}, ["a", "b", "c"]),
    ({"a": {"a"}}, ["a"]),
])
def test_find_cycle(graph, cycle):
  assert find_cycle(graph) == cycle
