"""gin files are data: statements that would run code are refused before gin sees them."""

import sys

import gin
import pytest

from signerf_jax import configs
from signerf_jax.errors import InputError
from signerf_jax.nerf import train


@pytest.fixture
def planted_module(tmp_path, monkeypatch):
  """A module on the import path that leaves a marker file behind if anything imports it."""
  marker = tmp_path / "imported"
  (tmp_path / "planted_payload.py").write_text(
      f"open({str(marker)!r}, 'w').write('ran')\n")
  monkeypatch.syspath_prepend(str(tmp_path))
  yield marker
  sys.modules.pop("planted_payload", None)
  gin.clear_config()


@pytest.mark.parametrize("statement", ["import planted_payload",
                                       "from planted_payload import anything",
                                       "import os.path as planted_payload"])
def test_an_import_in_a_gin_file_is_refused_naming_file_and_line(tmp_path, planted_module,
                                                                 statement):
  path = tmp_path / "hostile.gin"
  path.write_text(f"TrainConfig.steps = 10\n\n{statement}\n")
  with pytest.raises(InputError, match="line 3") as error:
    configs.parse_gin([path])
  assert error.value.path == str(path) and error.value.field == "import"
  assert not planted_module.exists()


def test_an_import_in_a_gin_param_is_refused(planted_module):
  with pytest.raises(InputError, match="would run code") as error:
    configs.parse_gin([], ["import planted_payload"])
  assert error.value.path == "gin_param"
  assert not planted_module.exists()


def test_an_included_file_is_checked_too_and_include_cycles_are_errors(tmp_path, planted_module):
  (tmp_path / "inner.gin").write_text("import planted_payload\n")
  outer = tmp_path / "outer.gin"
  outer.write_text(f"include {str(tmp_path / 'inner.gin')!r}\n")
  with pytest.raises(InputError, match="would run code") as error:
    configs.parse_gin([outer])
  assert error.value.path == str((tmp_path / "inner.gin").resolve())
  assert not planted_module.exists()
  (tmp_path / "inner.gin").write_text(f"include {str(outer)!r}\n")
  with pytest.raises(InputError, match="cycle"):
    configs.parse_gin([outer])


def test_bindings_still_apply_and_a_saved_config_reads_back(tmp_path):
  path = tmp_path / "good.gin"
  path.write_text("# a comment\nTrainConfig.steps = 7\nTrainConfig.learning_rate = 0.005\n")
  configs.parse_gin([path], ["TrainConfig.seed = 3"])
  assert (train.TrainConfig().steps, train.TrainConfig().seed) == (7, 3)
  saved = configs.save_gin_config(tmp_path)
  configs.parse_gin([saved])
  assert train.TrainConfig().learning_rate == 0.005
  gin.clear_config()


def test_bad_syntax_names_the_file_and_line(tmp_path):
  path = tmp_path / "broken.gin"
  path.write_text("TrainConfig.steps = 7\nTrainConfig.seed 3\n")
  with pytest.raises(InputError, match="line 2") as error:
    configs.parse_gin([path])
  assert error.value.path == str(path)


@pytest.mark.parametrize("path", sorted(configs.GIN_CONFIG_DIR.glob("*.gin")),
                         ids=lambda path: path.name)
def test_the_projects_own_gin_files_are_data(path):
  configs.check_gin_is_data(path.read_text(), path)
