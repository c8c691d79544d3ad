"""The catalogue's configuration and prompt cases (issue 68): a gin binding in a scope no command
builds (ignored before), gin bindings that recurse (macros referring back to themselves,
thousands of nested brackets), a gin file that is not UTF-8, and, with --strict, a prompt longer
than the text encoder reads or holding characters its tokenizer cannot encode (without --strict
those are warnings: tests/editing/test_input_checks.py). Each is a `signerf` command that must
end in one clear error naming the file or the parameter, before the command creates anything
(the shape of test_bad_input_catalogue.py's command cases)."""

from __future__ import annotations

import pytest

from test_bad_input_catalogue import assert_one_clear_error, copy, edit_argv, inputs  # noqa: F401

SCOPED_NAMES = ["original/TrainConfig", "finetune/TrainConfig", "retrain/TrainConfig",
                "first_iteration/GenerationOptions", "second_iteration/GenerationOptions"]


def train_argv(tmp_path, inputs, *extra: str) -> list[str]:
  return ["train", "--data", str(inputs["scene"]), "--run", str(tmp_path / "r"), *extra]


def with_prompt(argv: list[str], prompt: str) -> list[str]:
  argv[argv.index("--prompt") + 1] = prompt
  return argv


def binding_in_an_unknown_scope(tmp_path, inputs):
  return (train_argv(tmp_path, inputs, "--gin_param", "nosuchscope/TrainConfig.steps = -4"),
          ["gin_param: nosuchscope/TrainConfig.steps:", "gin scope 'nosuchscope'",
           "would be ignored", *SCOPED_NAMES], tmp_path / "r")


def binding_of_a_class_its_scope_does_not_build(tmp_path, inputs):
  return (edit_argv(tmp_path, inputs, "--gin_param", "first_iteration/TrainConfig.steps = 3"),
          ["first_iteration/TrainConfig.steps", "the commands build only GenerationOptions in it",
           *SCOPED_NAMES], tmp_path / "edit")


def misspelt_scope_in_a_gin_file(tmp_path, inputs):
  path = tmp_path / "edit.gin"
  path.write_text("finetune/TrainConfig.steps = 3\nfintune/TrainConfig.max_seconds = 5.0\n")
  return (edit_argv(tmp_path, inputs, "--gin_file", str(path)),
          [str(path), "fintune/TrainConfig.max_seconds", "line 2", "gin scope 'fintune'"],
          tmp_path / "edit")


def macros_referring_to_each_other(tmp_path, inputs):
  path = tmp_path / "macros.gin"
  path.write_text("TrainConfig.steps = %a\na = %b\nb = %a\n")
  return (train_argv(tmp_path, inputs, "--gin_file", str(path)),
          [str(path), "refer back to themselves", "`a = %b`", "`b = %a`"], tmp_path / "r")


def macro_cycle_through_gin_params(tmp_path, inputs):
  return (edit_argv(tmp_path, inputs, "--gin_param", "a = %b", "--gin_param", "b = %a"),
          ["gin_param: a:", "refer back to themselves"], tmp_path / "edit")


def configurable_referring_to_itself(tmp_path, inputs):
  return (train_argv(tmp_path, inputs, "--gin_param", "TrainConfig.steps = @TrainConfig()"),
          ["gin_param: TrainConfig.steps:", "refer back to themselves"], tmp_path / "r")


def thousands_of_nested_brackets(tmp_path, inputs):
  path = tmp_path / "deep.gin"
  path.write_text("TrainConfig.steps = 3\nTrainConfig.seed = " + "[" * 3000 + "]" * 3000 + "\n")
  return (train_argv(tmp_path, inputs, "--gin_file", str(path)),
          [str(path), "line 2", "brackets nest more than 100 levels deep"], tmp_path / "r")


def nested_brackets_in_a_gin_param(tmp_path, inputs):
  return (edit_argv(tmp_path, inputs, "--gin_param",
                    "SheetConfig.rows = " + "(" * 3000 + "1," + ")" * 3000),
          ["gin_param", "brackets nest more than 100 levels deep"], tmp_path / "edit")


def gin_file_not_utf8(tmp_path, inputs):
  path = tmp_path / "latin1.gin"
  path.write_bytes("TrainConfig.steps = 3\n# café\n".encode("latin-1"))
  return (train_argv(tmp_path, inputs, "--gin_file", str(path)),
          [str(path), "not UTF-8 text (byte 0xe9 on line 2)"], tmp_path / "r")


def saved_edit_config_not_utf8(tmp_path, inputs):
  (tmp_path / "edit").mkdir()
  saved = tmp_path / "edit" / "config.gin"
  saved.write_bytes(b"EditConfig.prompt = 'a red cow'\nEditConfig.negative_prompt = '\xff'\n")
  return (edit_argv(tmp_path, inputs), [str(saved), "not UTF-8 text"],
          tmp_path / "edit" / "stages.json")


def strict_prompt_longer_than_the_encoder_reads(tmp_path, inputs):
  argv = with_prompt(edit_argv(tmp_path, inputs, "--strict"), "a red cow with spots " * 4)
  return (argv, ["EditConfig.prompt", "longer than the 14 tokens",
                 "the end 'spots a red cow with spots' is cut off"],
          tmp_path / "edit" / "stages.json")


def strict_prompt_with_emoji(tmp_path, inputs):
  argv = with_prompt(edit_argv(tmp_path, inputs, "--strict"), "a red 🐄 cow")
  return (argv, ["EditConfig.prompt", "cannot encode '🐄'"], tmp_path / "edit" / "stages.json")


CONFIG_CASES = [
    binding_in_an_unknown_scope, binding_of_a_class_its_scope_does_not_build,
    misspelt_scope_in_a_gin_file, macros_referring_to_each_other, macro_cycle_through_gin_params,
    configurable_referring_to_itself, thousands_of_nested_brackets,
    nested_brackets_in_a_gin_param, gin_file_not_utf8, saved_edit_config_not_utf8,
    strict_prompt_longer_than_the_encoder_reads, strict_prompt_with_emoji,
]


@pytest.mark.parametrize("case", CONFIG_CASES, ids=lambda case: case.__name__)
def test_a_bad_configuration_or_prompt_is_one_clear_error(tmp_path, inputs, capsys, case):
  assert_one_clear_error(*case(tmp_path, inputs), capsys)
