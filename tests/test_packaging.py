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


def _setuptools_table():
  return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def _package_folder(package: str) -> Path:
  """Where a package's files are in the repository (pyproject.toml's package-dir, else its
  name's path)."""
  package_dir = _setuptools_table().get("package-dir", {})
  for prefix in sorted(package_dir, key=len, reverse=True):
    if package == prefix or package.startswith(prefix + "."):
      rest = package[len(prefix):].strip(".").split(".") if package != prefix else []
      return ROOT / package_dir[prefix] / Path(*rest)
  return ROOT / Path(*package.split("."))


def test_every_package_folder_is_shipped():
  """The package list is written out (gin_configs/ maps onto signerf_jax.gin_configs, which
  discovery cannot find): every folder under signerf_jax/ and gin_configs/ must be in it, those of
  Python files and those of data alike."""
  packages = set(_setuptools_table()["packages"])
  roots = {"signerf_jax": ROOT / "signerf_jax",
           "signerf_jax.gin_configs": _package_folder("signerf_jax.gin_configs")}
  folders = {".".join([package, *folder.relative_to(root).parts])
             for package, root in roots.items()
             for folder in [root, *root.rglob("*")]
             if folder.is_dir() and "__pycache__" not in folder.parts}
  assert folders == packages, (sorted(folders - packages), sorted(packages - folders))


def test_package_data_covers_every_data_file():
  """Every file under signerf_jax/ and gin_configs/ that is not Python (the gin configs, the
  default model's weights, the CPU attention kernel's source) matches a package-data glob, so the
  wheel carries what the package reads at run time (tests/test_wheel.py installs one)."""
  package_data = _setuptools_table()["package-data"]
  shipped = set()
  for package, patterns in package_data.items():
    folder = _package_folder(package)
    for pattern in patterns:
      shipped |= {path.resolve() for path in folder.glob(pattern) if path.is_file()}
  data_files = {path.resolve()
                for folder in (ROOT / "signerf_jax", _package_folder("signerf_jax.gin_configs"))
                for path in folder.rglob("*")
                if path.is_file() and "__pycache__" not in path.parts
                and path.suffix not in (".py", ".pyc")}
  assert (ROOT / "gin_configs" / "demo.gin").resolve() in data_files
  assert (ROOT / "gin_configs" / "paper_scenes").is_dir()
  assert not data_files - shipped, sorted(str(path.relative_to(ROOT))
                                          for path in data_files - shipped)


def test_licence_and_citation():
  """LICENSE is the Apache License 2.0 that pyproject.toml declares; both it and CITATION.cff
  travel in the wheel (license-files); the citation names this version and the paper."""
  yaml = pytest.importorskip("yaml")
  assert PROJECT["license"] == "Apache-2.0"
  assert set(PROJECT["license-files"]) == {"LICENSE", "CITATION.cff"}
  licence = (ROOT / "LICENSE").read_text()
  assert licence.split()[:4] == ["Apache", "License", "Version", "2.0,"]
  assert "END OF TERMS AND CONDITIONS" in licence
  citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
  assert citation["cff-version"] == "1.2.0"
  assert str(citation["version"]) == PROJECT["version"]
  assert citation["license"] == PROJECT["license"]
  paper = citation["preferred-citation"]
  assert paper["type"] == "conference-paper"
  assert paper["title"] == "SIGNeRF: Scene Integrated Generation for Neural Radiance Fields"
  assert [author["family-names"] for author in paper["authors"]] == [
      "Dihlmann", "Engelhardt", "Lensch"]
  assert paper["year"] == 2024
