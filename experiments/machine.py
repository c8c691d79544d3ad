"""What a result came from, recorded beside its numbers: the machine, the code's commit, and
(`settings_record`) the configuration and the seeds."""

from __future__ import annotations

import dataclasses
import os
import platform
import subprocess
from pathlib import Path
from typing import Any, Mapping

import jax

REPOSITORY_ROOT = Path(__file__).resolve().parent.parent


def cpu_model() -> str:
  """The CPU's model name, family and model number from /proc/cpuinfo ("" where there is none):
  the same platform string covers hosts whose speed differs by 2x (Zen 3 / 4 / 5)."""
  try:
    lines = Path("/proc/cpuinfo").read_text().splitlines()
  except OSError:
    return ""
  fields: dict[str, str] = {}
  for line in lines:
    key, _, value = line.partition(":")
    fields.setdefault(key.strip(), value.strip())
  return (f"{fields.get('model name', '?')}, CPU family {fields.get('cpu family', '?')} "
          f"model {fields.get('model', '?')}")


def _git(*arguments: str) -> subprocess.CompletedProcess | None:
  try:
    return subprocess.run(["git", *arguments], cwd=REPOSITORY_ROOT, capture_output=True,
                          text=True, timeout=30, check=False)
  except (OSError, subprocess.TimeoutExpired):
    return None


def code_version() -> dict[str, Any]:
  """{"commit": the repository's HEAD, "uncommitted_changes": whether tracked files differ from
  it}; both None outside a git checkout (an installed wheel, no git). Read-only: `git diff`
  does not rewrite the index, as `git status` may."""
  head = _git("rev-parse", "HEAD")
  if head is None or head.returncode != 0:
    return {"commit": None, "uncommitted_changes": None}
  # Exit code 1: tracked files differ from HEAD (untracked files do not count).
  differs = _git("diff", "--quiet", "HEAD", "--")
  return {"commit": head.stdout.strip(),
          "uncommitted_changes": None if differs is None else differs.returncode == 1}


def record(**extra: Any) -> dict[str, Any]:
  """Platform, CPU model and count, JAX version, the code's commit (`code_version`), `extra`
  fields and the 1/5/15-minute load averages now (call it when the measurement starts)."""
  return {"platform": platform.platform(), "cpu": cpu_model(), "cpu_count": os.cpu_count(),
          "jax": jax.__version__, **code_version(), **extra,
          "load_average_at_start": os.getloadavg()}


def seeds(settings: Any, path: str = "") -> dict[str, Any]:
  """Every seed in `settings` (dataclasses, mappings, tuples and lists of them, nested): the
  fields named `seed`, `seeds` or `..._seed`, by their path, e.g. {"training.original.seed": 0}."""
  if dataclasses.is_dataclass(settings) and not isinstance(settings, type):
    items = [(field.name, getattr(settings, field.name))
             for field in dataclasses.fields(settings)]
  elif isinstance(settings, Mapping):
    items = list(settings.items())
  elif isinstance(settings, (tuple, list)):
    items = list(enumerate(settings))
  else:
    return {}
  found: dict[str, Any] = {}
  for name, value in items:
    name = str(name)
    if name in ("seed", "seeds") or name.endswith("_seed"):
      found[path + name] = list(value) if isinstance(value, tuple) else value
    else:
      found.update(seeds(value, f"{path}{name}."))
  return found


def settings_record(gin_config: str, **settings: Any) -> dict[str, Any]:
  """The configuration a result ran with: {"gin_config": the gin bindings in effect
  (`gin.config_str()`), "seeds": every seed in `settings` (`seeds`), by keyword then path}."""
  return {"gin_config": gin_config,
          "seeds": {f"{name}.{path}": seed for name, part in settings.items()
                    for path, seed in seeds(part).items()}}
