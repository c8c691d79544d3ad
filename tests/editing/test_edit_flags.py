"""The edit commands' flags are shorthand for gin bindings: what they bind, and the settings that
result."""

import pytest

from signerf_jax import cli, configs, files
from signerf_jax.default_model import export
from signerf_jax.default_model import model as model_lib
from signerf_jax.editing import commands, generation
from signerf_jax.editing.commands import evaluate as evaluate_command
from signerf_jax.editing.config import (DEFAULT_MODEL_DIR, TRAINING_RUNS, EditConfig,
                                        EditSettings, SelectionConfig)
from signerf_jax.errors import InputError


@pytest.fixture
def clear_gin():
  yield
  configs.parse_gin()


def parsed(*flags: str):
  argv = ["edit", "--edit", "o", *flags]
  return cli.build_parser(argv).parse_args(argv)


def test_max_seconds_budgets_every_nerf_training_of_the_edit(clear_gin):
  bindings = commands.flag_bindings(parsed("--prompt", "a cow", "--box", "0", "0", "0", "1", "1",
                                           "1", "--max_seconds", "90"))
  configs.parse_gin([], bindings)
  settings = commands.edit_settings()
  assert {run: settings.training[run].max_seconds for run in TRAINING_RUNS} == {
      run: 90.0 for run in TRAINING_RUNS}


def test_a_budget_for_one_run_is_a_gin_binding(clear_gin):
  bindings = commands.flag_bindings(parsed("--prompt", "a cow", "--box", "0", "0", "0", "1", "1",
                                           "1"))
  configs.parse_gin([], bindings + ["finetune/TrainConfig.max_seconds = 30.0"])
  settings = commands.edit_settings()
  assert settings.training["finetune"].max_seconds == 30.0
  assert settings.training["original"].max_seconds is None


BOX = ("--prompt", "a cow", "--box", "0", "0", "0", "1", "1", "1")


def test_the_mask_growth_is_the_models_unless_bound(clear_gin, tmp_path):
  configs.parse_gin([], commands.flag_bindings(parsed(*BOX)))
  assert commands.edit_settings().selection.dilation_radius == export.MASK_DILATION_RADIUS == 8.0
  files.write_json(tmp_path / "model_index.json", {"_class_name": "AnyPipeline"})
  configs.parse_gin([], commands.flag_bindings(parsed(*BOX, "--model", str(tmp_path))))
  assert commands.edit_settings().selection.dilation_radius == generation.DEFAULT_MASK_DILATION
  configs.parse_gin([], commands.flag_bindings(parsed(*BOX)) + [
      "SelectionConfig.dilation_radius = 16.0"])
  assert commands.edit_settings().selection.dilation_radius == 16.0


def test_the_shipped_model_records_the_growth_its_export_writes():
  architecture = model_lib.Architecture()
  assert export.model_index(architecture)[generation.MASK_DILATION_KEY] == (
      generation.recommended_mask_dilation(DEFAULT_MODEL_DIR))


@pytest.mark.parametrize("value", [-1.0, "8", None, True])
def test_a_bad_recorded_growth_names_the_file_and_key(tmp_path, value):
  files.write_json(tmp_path / "model_index.json", {generation.MASK_DILATION_KEY: value})
  with pytest.raises(InputError, match="model_index.json.*_signerf_mask_dilation_radius"):
    generation.recommended_mask_dilation(tmp_path)


def test_a_model_without_an_index_grows_masks_by_the_default(tmp_path):
  assert generation.recommended_mask_dilation(tmp_path) == generation.DEFAULT_MASK_DILATION


def test_settings_without_a_mask_growth_are_refused():
  with pytest.raises(InputError, match="SelectionConfig.dilation_radius"):
    EditSettings(edit=EditConfig(prompt="a cow"),
                 selection=SelectionConfig(box_min=(0.0,) * 3, box_max=(1.0,) * 3))


def test_up_mesh_up_and_heading_bind_the_standing_proxy(clear_gin):
  configs.parse_gin([], commands.flag_bindings(parsed(
      "--prompt", "a cow", "--proxy", "primitive:cow", "--on_ground", "1", "2", "3", "--up", "0",
      "0", "1", "--mesh_up", "0", "0", "1", "--heading", "15")))
  selection = commands.edit_settings().selection
  assert (selection.up, selection.mesh_up, selection.heading_degrees) == (
      (0.0, 0.0, 1.0), (0.0, 0.0, 1.0), 15.0)


def test_eval_takes_gin_for_an_edit_only():
  argv = ["eval", "--run", "r", "--gin_param", "EvaluationConfig.independent_views = 12"]
  args = cli.build_parser(argv).parse_args(argv)
  with pytest.raises(InputError, match="--edit"):
    evaluate_command.check_arguments(args)
  argv[1:3] = ["--edit", "e"]
  evaluate_command.check_arguments(cli.build_parser(argv).parse_args(argv))
