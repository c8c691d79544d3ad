"""The edit commands' flags are shorthand for gin bindings: what they bind, and the settings that
result."""

import pytest

from signerf_jax import cli, configs
from signerf_jax.editing import commands
from signerf_jax.editing.config import TRAINING_RUNS


@pytest.fixture
def clear_gin():
  yield
  configs.parse_gin()


def parsed(*flags: str):
  argv = ["edit", "--out", "o", *flags]
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
