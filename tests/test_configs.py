"""gin at the edge: files are data (statements that would run code are refused before gin sees
them), the library's classes ignore gin, and `configs.build` makes them from the bindings."""

import dataclasses
import importlib
import pkgutil
import sys

import gin
import pytest

from signerf_jax import configs, default_model
from signerf_jax.editing import commands
from signerf_jax.errors import InputError
from signerf_jax.nerf import capacity, train

# What the experiments' scripts register themselves (they are not importable modules).
EXPERIMENT_CONFIGURABLES = ["ablations", "bench_nerf", "benchmark", "scaling"]


@pytest.fixture
def clear_gin():
  yield
  gin.clear_config()


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


def test_bindings_still_apply_and_a_saved_config_reads_back(tmp_path, clear_gin):
  path = tmp_path / "good.gin"
  path.write_text("# a comment\nTrainConfig.steps = 7\nTrainConfig.learning_rate = 0.005\n")
  configs.parse_gin([path], ["TrainConfig.seed = 3"])
  built = configs.build(train.TrainConfig)
  assert (built.steps, built.seed) == (7, 3)
  saved = configs.save_gin_config(tmp_path)
  configs.parse_gin([saved])
  assert configs.build(train.TrainConfig) == built


def test_build_applies_bindings_and_scopes_and_returns_the_plain_class(clear_gin):
  configs.parse_gin([], ["TrainConfig.steps = 7", "finetune/TrainConfig.seed = 2",
                         "CapacityRules.overrides = {'num_levels': 4}"])
  built = configs.build(train.TrainConfig)
  assert type(built) is train.TrainConfig and built == train.TrainConfig(steps=7)
  assert configs.build(train.TrainConfig, "finetune") == train.TrainConfig(steps=7, seed=2)
  assert configs.build(train.TrainConfig, "retrain") == built
  rules = configs.build(capacity.CapacityRules)
  assert rules == capacity.CapacityRules(overrides={"num_levels": 4})
  with gin.config_scope("finetune"):  # A scope the caller entered applies too.
    assert configs.build(train.TrainConfig).seed == 2


def test_the_plain_classes_ignore_bindings(clear_gin):
  configs.parse_gin([], ["TrainConfig.steps = 7", "CapacityRules.samples_per_batch = 1024"])
  assert train.TrainConfig().steps == 5000
  assert capacity.CapacityRules().samples_per_batch == 65536
  assert train.TrainConfig() != configs.build(train.TrainConfig)
  gin.clear_config()
  assert configs.build(train.TrainConfig) == train.TrainConfig()


def test_build_refuses_a_class_gin_does_not_bind():
  with pytest.raises(InputError, match="Capacity is not a class gin binds") as error:
    configs.build(capacity.Capacity)
  assert error.value.field == "cls"


def test_a_bound_value_the_class_rejects_is_an_input_error(clear_gin):
  configs.parse_gin([], ["CapacityRules.level_growth = 0.5"])
  with pytest.raises(InputError) as error:
    configs.build(capacity.CapacityRules)
  assert error.value.field == "CapacityRules.level_growth"


def test_every_configurable_is_a_frozen_dataclass_under_its_own_gin_name():
  table = configs.configurables()
  assert sorted(table.values()) == sorted([
      "TrainConfig", "CapacityRules", "DataConfig", "synthetic_scene", "synthetic_cameras",
      "consistency", "ReferencePlacement", "AttentionOptions", "GenerationOptions",
      "EditConfig", "SelectionConfig", "SheetConfig", "PreviewConfig",
      "UpdateConfig", "FinetuneConfig", "EvaluationConfig", "NerfConsistencySettings",
      "demo"])
  for cls in table:
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, cls
    assert cls.__module__.startswith("signerf_jax."), cls


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


@pytest.mark.parametrize("path", sorted(configs.GIN_CONFIG_DIR.rglob("*.gin")),
                         ids=lambda path: str(path.relative_to(configs.GIN_CONFIG_DIR)))
def test_the_projects_own_gin_files_bind_registered_names_only(path, clear_gin):
  """Every configurable a gin file names exists (the library's table, default_model's own, or
  an experiment script's) with the parameters it binds."""
  for module in pkgutil.iter_modules(default_model.__path__):
    importlib.import_module(f"{default_model.__name__}.{module.name}")
  configs.parse_gin([], finalize=False)
  gin.parse_config_files_and_bindings([str(path)], [], finalize_config=False,
                                      skip_unknown=EXPERIMENT_CONFIGURABLES)


def edit_bindings() -> list[str]:
  return ["EditConfig.prompt = 'a red cow'", "SelectionConfig.box_min = (0, 0, 0)",
          "SelectionConfig.box_max = (1, 1, 1)"]


@pytest.mark.parametrize("binding, problem", [
    ("nosuchscope/TrainConfig.steps = -4",
     "gin scope 'nosuchscope': no command builds anything in it"),
    ("first_iteration/TrainConfig.steps = 3",
     "gin scope 'first_iteration': the commands build only GenerationOptions in it"),
    ("finetune/EditConfig.prompt = 'x'",
     "gin scope 'finetune': the commands build only TrainConfig in it"),
])
def test_a_binding_in_a_scope_no_command_builds_is_refused_listing_the_scopes(binding, problem):
  with pytest.raises(InputError, match=problem) as error:
    configs.parse_gin([], [binding])
  assert error.value.path == "gin_param"
  assert error.value.field == binding.partition(" =")[0]
  for scope, gin_name in [("original", "TrainConfig"), ("finetune", "TrainConfig"),
                          ("retrain", "TrainConfig"), ("first_iteration", "GenerationOptions"),
                          ("second_iteration", "GenerationOptions")]:
    assert f"{scope}/{gin_name}" in str(error.value)


def test_an_unknown_scope_in_a_gin_file_names_the_file_and_line(tmp_path):
  path = tmp_path / "scoped.gin"
  path.write_text("TrainConfig.steps = 7\nfinetune/TrainConfig.seed = 2\n"
                  "fintune/TrainConfig.seed = 3\n")
  with pytest.raises(InputError, match="line 3: gin scope 'fintune'") as error:
    configs.parse_gin([path])
  assert error.value.path == str(path) and error.value.field == "fintune/TrainConfig.seed"


def test_the_registered_scopes_are_exactly_those_the_edit_builds(clear_gin, monkeypatch):
  """configs.scopes() lists what the commands build: no scope a command builds in is refused,
  and none is accepted that no command builds in."""
  built = []
  build = configs.build

  def recording_build(cls, scope=None):
    built.append((scope, cls))
    return build(cls, scope)

  monkeypatch.setattr(configs, "build", recording_build)
  configs.parse_gin([], edit_bindings())
  commands.edit_settings()
  assert {(scope, cls) for scope, cls in built if scope} == {
      (scope, cls) for scope, classes in configs.scopes().items() for cls in classes}


def test_build_refuses_a_scope_parse_gin_does_not_know(clear_gin):
  configs.parse_gin([], [])
  with pytest.raises(InputError, match="'finetuning' is not a gin scope") as error:
    configs.build(train.TrainConfig, "finetuning")
  assert error.value.field == "scope"


@pytest.mark.parametrize("bindings, field, cycle", [
    (["a = %b", "b = %a", "TrainConfig.steps = %a"], "a", "`a = %b` (gin_param, line 1) -> "
     "`b = %a` (gin_param, line 1)"),
    (["n = %n"], "n", "`n = %n`"),
    (["TrainConfig.steps = @TrainConfig()"], "TrainConfig.steps", "@TrainConfig()"),
    (["EditConfig.prompt = @TrainConfig()", "finetune/TrainConfig.seed = [1, {'k': %m}]",
      "m = @EditConfig()"], "EditConfig.prompt", "`m = @EditConfig()`"),
])
def test_bindings_that_refer_back_to_themselves_are_refused(clear_gin, bindings, field, cycle):
  with pytest.raises(InputError, match="refer back to themselves") as error:
    configs.parse_gin([], bindings)
  assert error.value.path == "gin_param" and error.value.field == field
  assert cycle in str(error.value)


def test_a_macro_cycle_across_a_file_and_a_parameter_names_the_file(tmp_path, clear_gin):
  path = tmp_path / "macros.gin"
  path.write_text("TrainConfig.steps = %a\na = %b\n")
  with pytest.raises(InputError, match="refer back to themselves") as error:
    configs.parse_gin([path], ["b = %a"])
  assert error.value.path == str(path) and error.value.field == "a"
  assert f"`a = %b` ({path}, line 2) -> `b = %a` (gin_param, line 1)" in str(error.value)


def test_macros_that_share_or_chain_without_a_cycle_still_apply(clear_gin):
  configs.parse_gin([], ["c = 3", "a = %c", "b = [%c, %a]", "TrainConfig.steps = %a",
                         "TrainConfig.seed = %c", "finetune/TrainConfig.steps = %c"])
  assert configs.build(train.TrainConfig) == train.TrainConfig(steps=3, seed=3)
  chain = [f"m{index} = %m{index + 1}" for index in range(3000)] + ["m3000 = 5"]
  configs.parse_gin([], chain + ["TrainConfig.seed = %m2990"])
  assert configs.build(train.TrainConfig).seed == 5


def test_a_chain_of_macros_too_long_to_evaluate_is_an_input_error(clear_gin):
  chain = [f"m{index} = %m{index + 1}" for index in range(3000)] + ["m3000 = 5"]
  configs.parse_gin([], chain + ["TrainConfig.seed = %m0"])  # No cycle: gin takes it...
  with pytest.raises(InputError, match="refer to one another too deeply") as error:
    configs.build(train.TrainConfig, "finetune")  # ... but would overflow Python's stack.
  assert error.value.field == "finetune/TrainConfig"


def test_a_macro_never_defined_is_named(clear_gin):
  with pytest.raises(InputError, match="%nosuch is used but never defined") as error:
    configs.parse_gin([], ["TrainConfig.steps = %nosuch"])
  assert error.value.field == "TrainConfig.steps"
  assert "\n" not in str(error.value)


@pytest.mark.parametrize("depth", [150, 3000])
def test_deeply_nested_brackets_are_refused_naming_the_file_and_line(tmp_path, depth):
  path = tmp_path / "deep.gin"
  path.write_text("TrainConfig.steps = 7\nTrainConfig.seed = " + "[" * depth + "]" * depth + "\n")
  with pytest.raises(InputError, match="line 2: brackets nest more than 100 levels deep") as error:
    configs.parse_gin([path])
  assert error.value.path == str(path)
  with pytest.raises(InputError, match="brackets nest more than 100") as error:
    configs.parse_gin([], ["TrainConfig.seed = " + "{0: " * depth + "0" + "}" * depth])
  assert error.value.path == "gin_param"


def test_brackets_within_the_limit_are_parsed(clear_gin):
  configs.parse_gin([], ["CapacityRules.overrides = {'a': " + "[" * 99 + "]" * 99 + "}"])


@pytest.mark.parametrize("included", [False, True])
def test_a_gin_file_that_is_not_utf8_is_named(tmp_path, included):
  latin1 = tmp_path / "latin1.gin"
  latin1.write_bytes("TrainConfig.steps = 7\nEditConfig.prompt = 'a café'\n".encode("latin-1"))
  path = latin1
  if included:
    path = tmp_path / "outer.gin"
    path.write_text(f"include {str(latin1)!r}\n")
  with pytest.raises(InputError, match=r"not UTF-8 text \(byte 0xe9 on line 2\)") as error:
    configs.parse_gin([path])
  assert error.value.path in (str(latin1), str(latin1.resolve()))


def test_gins_own_errors_are_one_line(clear_gin):
  with pytest.raises(InputError, match="No configurable matching 'NoSuch'") as error:
    configs.parse_gin([], ["NoSuch.steps = 3"])
  assert "\n" not in str(error.value)
