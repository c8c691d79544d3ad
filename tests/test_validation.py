"""The settings dataclasses check every field's type and range when built: from Python, from gin
(the error names the binding as written, scope included) and from command-line flags (argparse's
usage error names the flag)."""

import argparse
import dataclasses
import typing

import pytest

from signerf_jax import cli, configs, validation
from signerf_jax.data.synthetic import SceneSettings
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.editing.config import EditConfig, PreviewConfig, SelectionConfig
from signerf_jax.errors import InputError
from signerf_jax.nerf.capacity import CapacityRules
from signerf_jax.nerf.commands import DataConfig
from signerf_jax.nerf.train import TrainConfig


@pytest.fixture
def clear_gin():
  yield
  configs.parse_gin()


@pytest.mark.parametrize("cls", list(configs.configurables()), ids=lambda cls: cls.__name__)
def test_every_field_of_every_configurable_has_a_check_and_the_defaults_pass(cls):
  hints = typing.get_type_hints(cls, include_extras=True)
  for field in dataclasses.fields(cls):
    assert validation.describe(hints[field.name])  # Raises for an annotation with no check.
  required = {EditConfig: {"prompt": "a cow"},
              SelectionConfig: {"box_min": (0, 0, 0), "box_max": (1, 1, 1)}}
  validation.check_fields(cls(**required.get(cls, {})))


@pytest.mark.parametrize("make, field, allowed", [
    (lambda: TrainConfig(steps="abc"), "TrainConfig.steps", "an integer >= 1"),
    (lambda: TrainConfig(steps=-5), "TrainConfig.steps", "an integer >= 1"),
    (lambda: TrainConfig(steps=2.5), "TrainConfig.steps", "an integer >= 1"),
    (lambda: TrainConfig(steps=True), "TrainConfig.steps", "an integer >= 1"),
    (lambda: TrainConfig(learning_rate=-0.01), "TrainConfig.learning_rate", "> 0"),
    (lambda: TrainConfig(learning_rate=[1e-2, 1e-3]), "TrainConfig.learning_rate",
     "a finite number > 0"),
    (lambda: TrainConfig(learning_rate=float("nan")), "TrainConfig.learning_rate", "finite"),
    (lambda: TrainConfig(max_seconds=0.0), "TrainConfig.max_seconds", "> 0 or None"),
    (lambda: CapacityRules(rays_per_batch=0), "CapacityRules.rays_per_batch", ">= 1 or None"),
    (lambda: CapacityRules(level_growth=1.0), "CapacityRules.level_growth", "> 1"),
    (lambda: CapacityRules(overrides=[1]), "CapacityRules.overrides", "a mapping"),
    (lambda: DataConfig(eval_every=1), "DataConfig.eval_every", ">= 2 or None"),
    (lambda: DataConfig(scene_kind="indoor"), "DataConfig.scene_kind", "'unbounded'"),
    (lambda: DataConfig(scene_center=(0.0, 1.0)), "DataConfig.scene_center", "a tuple of 3"),
    (lambda: SelectionConfig(box_min=(0.0, float("nan"), 0.0), box_max=(1.0, 1.0, 1.0)),
     "SelectionConfig.box_min", "finite"),
    (lambda: SelectionConfig(kind="lasso"), "SelectionConfig.kind", "one of 'box', 'proxy'"),
    (lambda: EditConfig(prompt="a cow", nerf_update="both"), "EditConfig.nerf_update",
     "'retrain'"),
    (lambda: EditConfig(prompt=3), "EditConfig.prompt", "a string"),
    (lambda: PreviewConfig(seeds=(0, -1)), "PreviewConfig.seeds", "each an integer >= 0"),
    (lambda: GenerationOptions(strength=0.0), "GenerationOptions.strength", "in (0, 1]"),
    (lambda: GenerationOptions(num_inference_steps=4, strength=0.2), "GenerationOptions.strength",
     "no step to run"),
    (lambda: SceneSettings(background_color=(1.0, 1.5, 1.0)), "SceneSettings.background_color",
     "in [0, 1]"),
], ids=lambda value: value if isinstance(value, str) else "")
def test_a_bad_value_names_the_parameter_the_value_and_what_is_allowed(make, field, allowed):
  with pytest.raises(InputError) as error:
    make()
  assert error.value.field == field
  assert allowed in str(error.value)


def test_lists_become_tuples_and_good_values_are_kept():
  selection = SelectionConfig(box_min=[0, 0, 0], box_max=[1.0, 1.0, 1.0])
  assert selection.box_min == (0, 0, 0) and isinstance(selection.box_min, tuple)
  assert hash(selection)  # Frozen settings stay hashable.
  assert TrainConfig(learning_rate=1).learning_rate == 1  # An integer is a number.


@pytest.mark.parametrize("binding, cls, scope, field", [
    ('finetune/TrainConfig.steps = "abc"', TrainConfig, "finetune", "finetune/TrainConfig.steps"),
    ("TrainConfig.learning_rate = [0.1, 0.2]", TrainConfig, None, "TrainConfig.learning_rate"),
    ("CapacityRules.rays_per_batch = 0", CapacityRules, None, "CapacityRules.rays_per_batch"),
    ("synthetic_scene.ambient = 2.0", SceneSettings, None, "synthetic_scene.ambient"),
    ("second_iteration/GenerationOptions.strength = 1.5", GenerationOptions, "second_iteration",
     "second_iteration/GenerationOptions.strength"),
])
def test_a_bad_gin_binding_is_named_as_written(clear_gin, binding, cls, scope, field):
  configs.parse_gin([], [binding])
  with pytest.raises(InputError) as error:
    configs.build(cls, scope)
  assert error.value.field == field
  assert "In call to configurable" not in str(error.value)  # gin's own wrapping is dropped.


@pytest.mark.parametrize("argv, message", [
    (["train", "--data", "d", "--run", "o", "--steps", "0"],
     "argument --steps: must be an integer >= 1, got 0"),
    (["train", "--data", "d", "--run", "o", "--max_seconds", "-3"],
     "argument --max_seconds: must be a finite number > 0, got -3"),
    (["train", "--data", "d", "--run", "o", "--eval_every", "1"],
     "argument --eval_every: must be an integer >= 2, got 1"),
    (["render", "--run", "r", "--chunk_size", "0"], "argument --chunk_size: must be an integer"),
    (["edit", "--edit", "o", "--box", "0", "0", "nan", "1", "1", "1"],
     "argument --box: must be a finite number, got nan"),
    (["edit", "--edit", "o", "--size", "abc"], "argument --size: must be a finite number > 0"),
    (["preview", "--edit", "o", "--seeds", "1", "-2"], "argument --seeds: must be an integer >= 0"),
    (["synthesize", "--out", "o", "--seed", "x"], "argument --seed: must be an integer >= 0"),
])
def test_a_bad_flag_is_a_usage_error_naming_the_flag(capsys, argv, message):
  with pytest.raises(SystemExit) as exit_:
    cli.main(argv)
  assert exit_.value.code == 2
  assert message in capsys.readouterr().err


def test_argument_type_uses_the_fields_own_rule():
  parse = validation.argument_type(TrainConfig, "max_seconds")
  assert parse("1.5") == 1.5
  with pytest.raises(argparse.ArgumentTypeError, match="> 0"):
    parse("0")
