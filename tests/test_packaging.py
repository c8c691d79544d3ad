"""The install commands in the README name extras the package defines, and the accelerator
extras install the same JAX version as the CPU dependency."""

import re
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_every_extra_the_readme_installs_is_defined():
  readme = (ROOT / "README.md").read_text()
  named = set(re.findall(r"pip install -e '\.\[([\w-]+)\]'", readme))
  assert {"test", "cuda12", "cuda13", "tpu"} <= named
  assert named <= set(PROJECT["optional-dependencies"])


def test_accelerator_extras_pin_the_cpu_jax_version():
  cpu_jax, = [requirement for requirement in PROJECT["dependencies"]
              if re.match(r"jax\W", requirement)]
  version_range = cpu_jax[len("jax"):]
  for extra in ("cuda12", "cuda13", "tpu"):
    assert PROJECT["optional-dependencies"][extra] == [f"jax[{extra}]{version_range}"], extra
