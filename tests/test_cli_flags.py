"""Every `signerf` command's flags: one name per thing, each shown with its default, the old
spellings still working for a release (with a warning), and each command saying what it writes.

The parser of every subcommand is walked (`cli.build_parser` with the command's name imports
only that command's module and adds its options)."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys

import pytest

from signerf_jax import cli
from signerf_jax.data import load
from signerf_jax.editing import commands
from signerf_jax.editing.config import EditConfig, EditSettings, SelectionConfig
from signerf_jax.editing.stages import runner

# flag -> (the one thing it names in every command, a phrase its help says wherever it is).
CONCEPTS: dict[str, tuple[str, str]] = {
    "--data": ("the input dataset", "dataset directory"),
    "--run": ("a NeRF run directory (`signerf train`)", "`signerf train`"),
    "--edit": ("the edit directory", "edit directory"),
    "--out": ("the folder a command fills with new outputs (neither a run nor an edit)",
              "write"),
    "--up": ("the scene's up direction, which the proxy stands along", "scene's up direction"),
    "--mesh_up": ("the proxy's own up direction", "proxy's own up"),
    "--heading": ("a turn of the proxy about --up", "turn of the proxy about --up"),
    "--size": ("a standing proxy's largest side", "largest side"),
    "--size_fraction": ("the proxy's largest side as a fraction of the view", "fraction"),
    "--proxy": ("a proxy mesh file or primitive", "primitive:<"),
    "--view": ("a training view", "training view"),
    "--pixel": ("a pixel of that view", "pixel"),
    "--rectangle": ("a rectangle in a training view", "rectangle"),
    "--prompt": ("what to insert or show", "what"),
    "--negative_prompt": ("what not to show", "not show"),
    "--model": ("a diffusers ControlNet inpainting pipeline directory", "pipeline directory"),
    "--controlnet": ("a diffusers ControlNet directory", "ControlNet directory"),
    "--scheduler": ("the diffusion scheduler", "scheduler"),
    "--seed": ("a random seed", "seed"),
    "--seeds": ("the preview's seeds", "seed"),
    "--reroll": ("re-rolled candidate sheets", "re-rolled"),
    "--sheet": ("the sheet recipe to propagate", "sheet recipe"),
    "--box": ("a box selection", "box"),
    "--scale": ("the proxy's similarity scale", "scale"),
    "--rotation": ("the proxy's similarity rotation", "Euler angles"),
    "--translation": ("the proxy's similarity translation", "translation"),
    "--on_ground": ("where a standing proxy's footprint is centred", "footprint"),
    "--nerf_update": ("fine-tune or retrain", "retrain"),
    "--second_iteration": ("a second iteration", "once more"),
    "--strict": ("unknown prompt words are errors", "prompt word"),
    "--lpips": ("VGG-LPIPS weights", "VGG-LPIPS weights"),
    "--clip": ("a CLIP checkpoint", "CLIP checkpoint"),
    "--views_per_device": ("views inpainted per device", "per device"),
    "--max_seconds": ("a NeRF training's time budget in seconds", "time budget in seconds"),
    "--steps": ("training steps", "training steps"),
    "--redo": ("stages to run again", "again"),
    "--downscale": ("the dataset's image downscale", "image downscale"),
    "--eval_every": ("hold out every N-th view", "every N-th view"),
    "--held_out": ("views to hold out", "hold out"),
    "--scene_kind": ("the scene kind", "scene kind"),
    "--scene_center": ("the centre of the region modelled in detail", "centre"),
    "--scene_radius": ("that region's half-side", "half-side"),
    "--skip_eval": ("no evaluation after training", "evaluate"),
    "--start_over": ("train afresh", "afresh"),
    "--replay": ("train again what a run trained, step for step", "train again"),
    "--coordinator_address": ("process 0 of a run of several processes", "process 0"),
    "--num_processes": ("how many processes take part", "processes take part"),
    "--process_id": ("this process's index among them", "index among them"),
    "--split": ("which dataset views", "views"),
    "--video": ("a video: render's camera-path video, or the capture process reads", "video"),
    "--images": ("a folder of photos", "photos"),
    "--max_frames": ("frames kept from a video", "frames kept"),
    "--camera_model": ("the lens model", "distortion"),
    "--camera_per_image": ("a camera per image", "own camera"),
    "--matching": ("the image pairs matched", "pairs"),
    "--max_image_size": ("the image size features are found at", "pixels wide"),
    "--max_features": ("features per image", "features per image"),
    "--frames": ("the video's length", "video"),
    "--chunk_size": ("rays rendered at once", "rays rendered at once"),
    "--supersampling": ("rays per pixel", "N x N rays"),
    "--host": ("the address to serve on", "address to serve on"),
    "--port": ("the port to serve on", "port to serve on"),
    "--gin_file": ("a gin file", "gin file"),
    "--gin_param": ("a gin binding", "gin binding"),
    "--quiet": ("no progress bars", "progress bars"),
    "-h": ("help", "help"),
    "--help": ("help", "help"),
}

# command -> its old spellings: old flag -> new flag (deprecated aliases for one release).
RENAMED = {
    "train": {"--out": "--run"},
    "place": {"--out": "--edit"},
    "preview": {"--out": "--edit"},
    "edit": {"--out": "--edit"},
    "update": {"--out": "--edit"},
    "finetune": {"--out": "--edit"},
}

# The commands that fill --out (nothing else takes it).
OUT_COMMANDS = ("synthesize", "process", "render", "demo")


def subparser(command: str) -> argparse.ArgumentParser:
  """`signerf COMMAND`'s parser, with its options."""
  parser = cli.build_parser([command])
  choices = next(action.choices for action in parser._actions
                 if isinstance(action, argparse._SubParsersAction))
  return choices[command]


def options(command: str) -> list[argparse.Action]:
  return [action for action in subparser(command)._actions if action.option_strings]


def expanded_help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
  """The help `--help` prints for `action` (its default appended by the formatter)."""
  return " ".join(parser._get_formatter()._expand_help(action).split())


def stage_names(second_iteration: bool) -> list[str]:
  settings = EditSettings(
      edit=EditConfig(prompt="a cow", second_iteration=second_iteration),
      selection=SelectionConfig(box_min=(0.0,) * 3, box_max=(1.0,) * 3, dilation_radius=8.0))
  return [stage.name for stage in runner.pipeline_stages(settings)]


@pytest.mark.parametrize("command", cli.COMMANDS)
def test_every_option_shows_its_default(command):
  parser = subparser(command)
  for action in options(command):
    default = action.default
    if (default is None or default is False or default == "" or default == []
        or default is argparse.SUPPRESS):
      continue  # None to show; the help says what happens without the flag.
    assert "default" in expanded_help(parser, action), (command, action.option_strings)


@pytest.mark.parametrize("command", cli.COMMANDS)
def test_each_flag_names_one_thing_in_every_command(command):
  parser = subparser(command)
  for action in options(command):
    for flag in action.option_strings:
      assert flag in CONCEPTS, f"signerf {command} {flag}: add it to CONCEPTS"
      phrase = CONCEPTS[flag][1]
      assert phrase.lower() in expanded_help(parser, action).lower(), (
          f"signerf {command} {flag} is not {CONCEPTS[flag][0]}")
  flags = {flag for action in options(command) for flag in action.option_strings}
  assert ("--out" in flags) == (command in OUT_COMMANDS)


@pytest.mark.parametrize("command", cli.COMMANDS)
def test_old_spellings_are_hidden_from_help(command):
  text = subparser(command).format_help()
  for old in RENAMED.get(command, {}):
    assert not re.search(rf"(?<![\w-]){re.escape(old)}(?![\w-])", text), (command, old)


@pytest.mark.parametrize("command,old,new", [
    (command, old, new) for command, renamed in RENAMED.items() for old, new in renamed.items()])
@pytest.mark.parametrize("spelling", ["separate", "equals"])
def test_an_old_spelling_works_and_warns_once(capsys, command, old, new, spelling):
  argv = [command, *(["--data", "d"] if command == "train" else []),
          *(["--run", "r"] if command == "place" else []),
          *([old, "o"] if spelling == "separate" else [f"{old}=o"])]
  args = cli.build_parser(argv).parse_args(argv)
  assert getattr(args, new[2:]) == "o"
  assert capsys.readouterr().err == f"signerf {command}: {old} is deprecated, use {new}\n"


def test_the_new_spelling_does_not_warn(capsys):
  argv = ["train", "--data", "d", "--run", "o"]
  assert cli.build_parser(argv).parse_args(argv).run == "o"
  assert capsys.readouterr().err == ""


def test_an_old_spelling_stands_for_a_required_flag(capsys, tmp_path):
  # --run is required: --out gives it; the command then runs (here: stops at the missing data).
  assert cli.main(["train", "--data", str(tmp_path / "missing"), "--out",
                   str(tmp_path / "run")]) == 2
  err = capsys.readouterr().err.splitlines()
  assert err[0] == "signerf train: --out is deprecated, use --run"
  assert "dataset directory not found" in err[1]


def test_the_alias_helper_refuses_a_flag_it_would_shadow():
  parser = argparse.ArgumentParser()
  parser.add_argument("--out")
  with pytest.raises(ValueError, match="--out"):
    cli.deprecated_aliases(parser, parser.add_argument("--run"), "--out")


@pytest.mark.parametrize("command", ["edit", "preview", "update", "finetune"])
def test_redo_lists_the_stages_the_command_runs(command):
  parser = subparser(command)
  redo = next(action for action in options(command) if "--redo" in action.option_strings)
  listed = expanded_help(parser, redo).split("Stages:")[1]
  first, second = stage_names(False), stage_names(True)
  wanted = (second if command == "edit"
            else first[:first.index(commands.LAST_STAGE[command]) + 1])
  named = list(dict.fromkeys(word for word in re.findall(r"\b[a-z]+(?:_\d)?\b", listed)
                             if word in second))
  assert sorted(named) == sorted(wanted)  # All it runs, nothing else.
  assert [name for name in named if name in first] == [name for name in wanted if name in first]


def test_the_static_stage_list_is_the_runners():
  assert list(commands.STAGES) == stage_names(False)
  assert list(commands.command_stages("edit")) == stage_names(True)


@pytest.mark.parametrize("command", cli.COMMANDS)
def test_data_help_names_every_format(command):
  parser = subparser(command)
  for action in options(command):
    if "--data" in action.option_strings:
      text = expanded_help(parser, action).lower()
      assert all(name in text for name in load.FORMATS), (command, text)
      assert "neus/idr" in text


@pytest.mark.parametrize("command", cli.COMMANDS)
def test_every_command_says_what_it_writes(command):
  parser = subparser(command)
  description = parser.description
  assert "Writes" in description, command
  output_flag = parser.get_default("output_flag")
  if output_flag:  # The directory it fills, by its flag's name.
    assert output_flag.upper() in description, command


def test_preview_offers_no_flag_only_later_stages_read():
  flags = {flag for action in options("preview") for flag in action.option_strings}
  assert not flags & {"--seed", "--sheet", "--nerf_update", "--second_iteration", "--lpips",
                      "--clip", "--views_per_device"}
  assert {"--prompt", "--proxy", "--max_seconds", "--redo", "--seeds", "--reroll"} <= flags
  edit_flags = {flag for action in options("edit") for flag in action.option_strings}
  for command, unread in commands.UNREAD_FLAGS.items():
    command_flags = {flag for action in options(command) for flag in action.option_strings}
    assert {f"--{name}" for name in unread} <= edit_flags
    assert not command_flags & {f"--{name}" for name in unread}, command


@pytest.mark.parametrize("argv", [["preview", "--edit", "e", "--seed", "3"],
                                  ["train", "--data", "d", "--run", "r", "--step", "3"]])
def test_a_flag_has_one_spelling_no_abbreviation(capsys, argv):
  with pytest.raises(SystemExit) as exit_:
    cli.main(argv)
  assert exit_.value.code == 2
  assert f"unrecognized arguments: {argv[-2]}" in capsys.readouterr().err


def test_signerf_help_imports_no_command():
  code = ("import sys; from signerf_jax import cli; cli.build_parser([]).format_help(); "
          "print(sorted(name for name in sys.modules if name.split('.')[0] in "
          "('jax', 'numpy', 'gin')))")
  result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
  assert result.stdout.strip() == "[]"


@pytest.mark.parametrize("argv,flag", [
    (["train", "--data", "d", "--run"], "run"),
    (["preview", "--edit"], "edit"),
    (["place", "--run", "r", "--edit"], "edit"),
    (["synthesize", "--out"], "out"),
])
def test_an_output_path_that_is_a_file_is_refused_naming_its_flag(capsys, tmp_path, argv, flag):
  taken = tmp_path / "taken"
  taken.write_text("a file")
  assert cli.main([*argv, str(taken)]) == 2
  assert f"{taken}: {flag}: names a file" in capsys.readouterr().err


def test_a_run_directory_of_other_files_is_refused_naming_run(capsys, tmp_path):
  run = tmp_path / "run"
  run.mkdir()
  (run / "notes.txt").write_text("mine")
  assert cli.main(["train", "--data", str(tmp_path / "scene"), "--run", str(run)]) == 2
  assert f"{run}: run: holds files signerf did not write" in capsys.readouterr().err


def test_an_edit_directory_of_other_files_is_refused_naming_edit(capsys, tmp_path):
  edit = tmp_path / "edit"
  edit.mkdir()
  (edit / "notes.txt").write_text("mine")
  assert cli.main(["preview", "--edit", str(edit), "--data", str(tmp_path / "scene"),
                   "--prompt", "a cow", "--box", "0", "0", "0", "1", "1", "1", "--quiet"]) == 2
  assert f"{edit}: edit: holds files signerf did not write" in capsys.readouterr().err
