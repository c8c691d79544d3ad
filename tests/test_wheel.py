"""The wheel works from any folder: built from the project, installed into a fresh virtual
environment, `signerf demo --help` runs and the demo's gin config loads through the installed
package (gin_configs/ ships as signerf_jax.gin_configs), with every data file the package reads
at run time inside it. tests/test_packaging.py checks the same declarations without building."""

from __future__ import annotations

import json
import os
import re
import shutil
import site
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
# Each step takes seconds on an idle 2-core machine (the build ~5 s, the commands ~10 s); the
# bounds leave room for a machine busy with the rest of the suite.
BUILD_TIMEOUT = 300
COMMAND_TIMEOUT = 300

# Run by the fresh environment's Python from an unrelated folder: where the package came from,
# its gin configs (the demo's, a paper scene's) and its data files.
SNIPPET = textwrap.dedent("""
    import json
    from pathlib import Path

    import gin
    import signerf_jax
    from signerf_jax import configs
    from signerf_jax.diffusion import cpu_attention
    from signerf_jax.editing.config import DEFAULT_MODEL_DIR

    configs.parse_gin(["demo"])
    package = Path(signerf_jax.__file__).parent
    print(json.dumps({
        "package": str(package),
        "gin_config_dir": str(configs.GIN_CONFIG_DIR),
        "num_views": gin.query_parameter("synthetic_cameras.num_views"),
        "paper_scene": str(configs.resolve_gin_file("paper_scenes/field_cow")),
        "default_model": str(DEFAULT_MODEL_DIR),
        "kernel_source": cpu_attention.SOURCE.is_file(),
        "data_files": sorted(str(path.relative_to(package.parent))
                             for path in package.rglob("*") if path.is_file()
                             and "__pycache__" not in path.parts and path.suffix != ".py"),
    }))
""")


def _run(command, timeout, **kwargs) -> subprocess.CompletedProcess:
  result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False,
                          **kwargs)
  assert result.returncode == 0, (command, result.stdout[-3000:], result.stderr[-3000:])
  return result


def _project_copy(destination: Path) -> Path:
  """What the build reads (pyproject.toml, its readme and licence files, the package folders),
  copied so that the build writes nothing into the checkout (setuptools keeps a build/ folder
  beside pyproject.toml, whose stale files would also reach the next wheel)."""
  pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
  setuptools = pyproject["tool"]["setuptools"]
  names = ["pyproject.toml", pyproject["project"]["readme"], *pyproject["project"]["license-files"],
           *{package.split(".")[0] for package in setuptools["packages"]},
           *setuptools.get("package-dir", {}).values()]
  ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
  for name in names:
    source = ROOT / name
    if source.is_dir():
      shutil.copytree(source, destination / name, ignore=ignore)
    else:
      (destination / name).parent.mkdir(parents=True, exist_ok=True)
      shutil.copy2(source, destination / name)
  return destination


def _expected_data_files() -> set[str]:
  """Every non-Python file of the package's folders, as the wheel must hold it."""
  folders = {ROOT / "signerf_jax": "signerf_jax", ROOT / "gin_configs": "signerf_jax/gin_configs"}
  return {f"{installed}/{path.relative_to(folder).as_posix()}"
          for folder, installed in folders.items() for path in folder.rglob("*")
          if path.is_file() and "__pycache__" not in path.parts
          and path.suffix not in (".py", ".pyc")}


def test_the_wheel_installs_and_runs_from_any_folder(tmp_path):
  project = _project_copy(tmp_path / "project")
  wheels = tmp_path / "wheels"
  _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
        "-w", str(wheels), str(project)], BUILD_TIMEOUT)
  wheel, = wheels.glob("signerf_jax-*.whl")

  environment = tmp_path / "venv"
  _run([sys.executable, "-m", "venv", "--without-pip", str(environment)], COMMAND_TIMEOUT)
  python = environment / "bin" / "python"
  _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
        "--no-index", str(wheel)], BUILD_TIMEOUT)
  new_site_packages = Path(_run([str(python), "-c",
                                 "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                COMMAND_TIMEOUT).stdout.strip())
  # The dependencies come from this environment: a path line in a .pth adds the folder without
  # running the .pth files inside it, so this environment's editable install of signerf_jax
  # (a .pth and its import finder) stays out.
  (new_site_packages / "dependencies.pth").write_text(
      "".join(f"{path}\n" for path in site.getsitepackages()))

  elsewhere = tmp_path / "elsewhere"
  elsewhere.mkdir()
  env = {name: value for name, value in os.environ.items()
         if name not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV")}
  env["HOME"] = str(tmp_path / "home")  # no user configuration or cache of this machine

  help_text = _run([str(environment / "bin" / "signerf"), "demo", "--help"], COMMAND_TIMEOUT,
                   cwd=elsewhere, env=env).stdout
  assert help_text.startswith("usage:") and "demo" in help_text

  found = json.loads(_run([str(python), "-c", SNIPPET], COMMAND_TIMEOUT, cwd=elsewhere,
                          env=env).stdout.splitlines()[-1])
  package = Path(found["package"])
  assert package == new_site_packages / "signerf_jax"
  assert Path(found["gin_config_dir"]) == package / "gin_configs"
  demo_views, = re.findall(r"^synthetic_cameras\.num_views\s*=\s*(\d+)",
                           (ROOT / "gin_configs" / "demo.gin").read_text(), re.MULTILINE)
  assert found["num_views"] == int(demo_views)
  assert Path(found["paper_scene"]) == package / "gin_configs" / "paper_scenes" / "field_cow.gin"
  assert Path(found["default_model"]) == package / "default_model" / "weights"
  assert found["kernel_source"]
  assert set(found["data_files"]) == _expected_data_files()
