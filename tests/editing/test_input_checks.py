"""An edit checks its inputs before its first stage: missing directories and unknown prompt
words are reported in a second, not after the original NeRF has trained."""

import dataclasses

import pytest

from signerf_jax.editing.config import EditConfig, EditSettings, SelectionConfig
from signerf_jax.editing.stages import inputs
from signerf_jax.errors import InputError

BOX = SelectionConfig(box_min=(0.0, 0.0, 0.0), box_max=(1.0, 1.0, 1.0), dilation_radius=24.0)


def settings(**edit) -> EditSettings:
  return EditSettings(edit=EditConfig(**{"prompt": "a red cow", **edit}), selection=BOX)


def test_a_prompt_the_shipped_model_knows_passes_without_warnings():
  assert inputs.check_inputs(settings()) == []


def test_an_unknown_prompt_word_is_a_warning_naming_it_and_the_known_words():
  warnings = inputs.check_inputs(settings(prompt="a red armadillo",
                                          negative_prompt="blurry zorblax"))
  assert len(warnings) == 2
  assert warnings[0].startswith("EditConfig.prompt: the model does not know 'armadillo'")
  assert " cow " in warnings[0] and "words: " in warnings[0]
  assert warnings[1].startswith("EditConfig.negative_prompt:") and "'zorblax'" in warnings[1]


def test_with_strict_prompt_an_unknown_word_is_an_error():
  with pytest.raises(InputError, match="does not know 'armadillo'") as error:
    inputs.check_inputs(settings(prompt="an armadillo", strict_prompt=True))
  assert error.value.field == "EditConfig.prompt"


@pytest.mark.parametrize("field, value", [("data", "/nonexistent/scene"),
                                          ("original_run", "/nonexistent/run"),
                                          ("model", "/nonexistent/model")])
def test_a_missing_directory_is_named_before_any_stage(field, value):
  with pytest.raises(InputError) as error:
    inputs.check_inputs(settings(**{field: value}))
  assert error.value.path == value
  assert error.value.field == f"EditConfig.{field}"


def test_a_missing_proxy_mesh_is_named_before_any_stage():
  selection = SelectionConfig(kind="proxy", proxy="/nonexistent/cow.obj",
                              ground_position=(0.0, 0.0, 0.0), dilation_radius=24.0)
  with pytest.raises(InputError, match="proxy mesh file not found") as error:
    inputs.check_inputs(dataclasses.replace(settings(), selection=selection))
  assert error.value.field == "proxy"


LONG_PROMPT = "a red cow with spots " * 4  # 20 words; the shipped model reads 14.
CUT_END = "spots a red cow with spots"


@pytest.mark.parametrize("prompt, problem", [
    (LONG_PROMPT, f"longer than the 14 tokens the model's text encoder reads: the end "
                  f"{CUT_END!r} is cut off"),
    ("a red 🐄 cow ✨", "the model's tokenizer cannot encode '🐄', '✨': its text encoder does "
                       "not see them"),
])
def test_a_prompt_cut_short_or_losing_characters_is_a_warning_naming_what_is_lost(prompt,
                                                                                  problem):
  assert inputs.check_inputs(settings(prompt=prompt)) == [f"EditConfig.prompt: {problem}"]
  assert inputs.check_inputs(settings(negative_prompt=prompt)) == [
      f"EditConfig.negative_prompt: {problem}"]


@pytest.mark.parametrize("field", ["prompt", "negative_prompt"])
@pytest.mark.parametrize("prompt, problem", [(LONG_PROMPT, f"the end {CUT_END!r} is cut off"),
                                             ("a red cow 🐄", "cannot encode '🐄'")])
def test_with_strict_prompt_a_cut_or_lost_character_is_an_error(field, prompt, problem):
  with pytest.raises(InputError, match=problem) as error:
    inputs.check_inputs(settings(**{field: prompt, "strict_prompt": True}))
  assert error.value.field == f"EditConfig.{field}"
