"""The edit's `signerf` subcommands (shared flags and helpers here): `edit` runs the whole
pipeline; `preview`, `update` and `finetune` run it up to their stage (earlier stages run first
if needed, finished ones are skipped); `eval --edit` evaluates. This is where gin meets the
editing code: `edit_settings` builds the `EditSettings` every stage reads from the bindings.

The flags describing the edit (--data, --prompt, --box / --proxy, --model, ...) are shorthand for
gin bindings of `editing.config` and are needed only when the edit directory is created: they
are saved in EDIT/config.gin, which every later command reads first (flags given again override
it, and every stage whose settings changed runs again). A command offers only the flags its
stages read (`UNREAD_FLAGS`).

    signerf preview --edit edits/cow --data scenes/field --prompt "a red cow" \\
        --proxy cow.obj --on_ground 0.1 -0.3 0 --size 0.5      # candidate sheets, seeds 0-3
    signerf preview --edit edits/cow --reroll 2/1,4@7           # sheet 2, tiles 1 and 4 again
    signerf edit --edit edits/cow --sheet 2/1,4@7                # the rest, with that sheet
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import typing
from pathlib import Path
from typing import Callable

import gin

from signerf_jax import cli, configs
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.editing import generation, stages
from signerf_jax.editing.commands import training_process
from signerf_jax.editing.config import (GENERATION_SCOPES, TRAINING_RUNS, EditConfig,
                                        EditSettings, EvaluationConfig, FinetuneConfig,
                                        NerfConsistencySettings, NerfUpdate, PRIMITIVE_PREFIX,
                                        PreviewConfig, SchedulerOverride, SelectionConfig,
                                        SheetConfig, UpdateConfig)
from signerf_jax.errors import InputError
from signerf_jax.geometry.reference_cameras import ReferencePlacement
from signerf_jax.metrics.consistency import ConsistencySettings
from signerf_jax.nerf.capacity import CapacityRules
from signerf_jax.nerf.train import TrainConfig
from signerf_jax.validation import argument_type

# command -> the stage it runs up to.
LAST_STAGE = {"edit": "evaluate", "preview": "preview", "update": "dataset",
              "finetune": "finetune", "eval": "evaluate", "demo": "evaluate"}

# The pipeline's stages in order (`stages.runner.pipeline_stages`, named here so that --help
# need not build settings; tests/test_cli_flags.py keeps the two equal), and those
# --second_iteration adds before "evaluate".
STAGES = ("original", "select", "reference", "preview", "sheet", "views", "update", "dataset",
          "finetune", "evaluate")
SECOND_ITERATION_STAGES = ("reference_2", "sheet_2", "update_2", "dataset_2", "finetune_2")

# command -> the flags of `add_edit_arguments` its stages never read, which it does not offer
# (given to a later command, they are saved in EDIT/config.gin as any flag is).
UNREAD_FLAGS = {
    "preview": ("seed", "sheet", "nerf_update", "second_iteration", "lpips", "clip",
                "views_per_device"),
    "update": ("nerf_update", "second_iteration", "lpips", "clip"),
    "finetune": ("second_iteration", "clip"),
    "edit": (),
}

# The placement flags, one meaning in every command (`signerf place` too).
UP_HELP = ("the scene's up direction in the dataset's own units, which the proxy stands along "
           "and --heading turns it about")
MESH_UP_HELP = "the proxy's own up direction, stood along --up"
HEADING_HELP = "turn of the proxy about --up, in degrees"


def gin_value(value) -> str:
  """A Python value as a gin literal (strings, numbers, booleans, tuples)."""
  if isinstance(value, list):
    value = tuple(value)
  return repr(value)


def command_stages(command: str) -> tuple[str, ...]:
  """The stages `command` runs (some or all of them), in order; `edit`'s include
  SECOND_ITERATION_STAGES."""
  if command in ("edit", "eval", "demo"):
    return STAGES[:-1] + SECOND_ITERATION_STAGES + STAGES[-1:]
  return STAGES[:STAGES.index(LAST_STAGE[command]) + 1]


def redo_help(command: str) -> str:
  """--redo's help: the stages `command` runs, by name."""
  names = [name for name in command_stages(command) if name not in SECOND_ITERATION_STAGES]
  second = [name for name in command_stages(command) if name in SECOND_ITERATION_STAGES]
  return ("run this stage (and every stage after it) again; repeatable. Stages: "
          + ", ".join(names)
          + (f" (with --second_iteration also {', '.join(second)} before evaluate)"
             if second else ""))


def add_edit_arguments(parser: argparse.ArgumentParser, command: str | None = None) -> None:
  """The flags shared by edit, preview, update and finetune (`command`, by default the one
  `parser` is named after): the ones its stages read (`UNREAD_FLAGS`)."""
  if command is None:
    command = parser.prog.rsplit(" ", 1)[-1]
  command = command if command in UNREAD_FLAGS else "edit"
  unread = set(UNREAD_FLAGS[command])

  def offer(group, flag: str, **kwargs) -> None:
    if flag[2:] not in unread:
      group.add_argument(flag, **kwargs)

  cli.add_output_argument(parser, "--edit", deprecated=("--out",), required=True,
                          help="the edit directory: new or empty (created), or an edit signerf "
                          "wrote (resumed; its config.gin is read first)")
  _add_inputs(parser.add_argument_group(
      "inputs (saved in EDIT/config.gin; left out, the saved value holds, else the default)"),
      offer)
  _add_selection(parser.add_argument_group(
      "selection (saved as the inputs are; in the dataset's own world units unless "
      "SelectionConfig.frame)"))
  _add_how(parser.add_argument_group("how"), offer, command)
  add_common_arguments(parser)


def _add_inputs(data, offer) -> None:
  """The edit's inputs: the dataset, its NeRF, the prompts, the diffusion model."""
  data.add_argument("--data", help=cli.DATA_HELP + "; default: the dataset --run was trained on")
  data.add_argument("--downscale", type=argument_type(EditConfig, "downscale"),
                    help="integer image downscale of the dataset (default: "
                    f"{EditConfig.downscale})")
  data.add_argument("--run", help="an already trained NeRF of the dataset (`signerf train`); "
                    "default: the edit trains one in EDIT/original/")
  data.add_argument("--prompt", help="what the edited region should show")
  data.add_argument("--negative_prompt", help="what it should not show (default: nothing)")
  offer(data, "--seed", type=argument_type(EditConfig, "seed"),
        help=f"seed of the image set update and the default sheet (default: {EditConfig.seed})")
  data.add_argument("--model", help="diffusers ControlNet inpainting pipeline directory, e.g. "
                    "SD 1.5 inpainting (default: the shipped model)")
  data.add_argument("--controlnet", help="diffusers ControlNet directory (depth or inpaint), "
                    "replacing the pipeline's (default: the pipeline's own)")
  data.add_argument("--scheduler", choices=typing.get_args(SchedulerOverride)[1:],
                    help="override the checkpoint's scheduler (default: the checkpoint's)")


def _add_selection(where) -> None:
  """Where to edit: a box, or a proxy placed by a similarity transform or standing on the
  ground (--up, --mesh_up and --heading mean what `signerf place`'s do)."""
  where.add_argument("--box", type=argument_type(float), nargs=6,
                     metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                     help="shape selection: axis-aligned box min and max corners")
  where.add_argument("--proxy", help="proxy selection: a mesh file or primitive:<box, sphere, "
                     "cylinder, capsule, cow>")
  where.add_argument("--scale", type=argument_type(SelectionConfig, "scale"),
                     help="proxy similarity transform: scale (default: "
                     f"{SelectionConfig.scale})")
  where.add_argument("--rotation", type=argument_type(float), nargs=3, metavar=("RX", "RY", "RZ"),
                     help="proxy similarity transform: Euler angles in degrees (x, y, z; "
                     "default: 0 0 0)")
  where.add_argument("--translation", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help="proxy similarity transform: translation (default: 0 0 0)")
  where.add_argument("--on_ground", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help="instead stand the proxy upright with its footprint centred here, as "
                     "`signerf place` does")
  where.add_argument("--size", type=argument_type(SelectionConfig, "ground_size"),
                     help="standing proxy: its largest side (default: "
                     f"{SelectionConfig.ground_size})")
  where.add_argument("--heading", type=argument_type(float),
                     help=f"standing proxy: {HEADING_HELP} (default: "
                     f"{SelectionConfig.heading_degrees})")
  where.add_argument("--up", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help=f"standing proxy: {UP_HELP} (default: the one `signerf place` "
                     "saved, else the cameras' mean up)")
  where.add_argument("--mesh_up", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help=f"standing proxy: {MESH_UP_HELP} (default: "
                     f"{' '.join(f'{value:g}' for value in SelectionConfig.mesh_up)}, +y as the "
                     "shared meshes)")


def _add_how(how, offer, command: str) -> None:
  """How the edit runs: the sheet, the NeRF update, its checks, budgets and redone stages."""
  offer(how, "--sheet", help="the sheet recipe to propagate: SEED or SEED/TILE,TILE@SEED "
        "(`signerf preview` shows candidates; default: the --seed sheet)")
  offer(how, "--nerf_update", choices=typing.get_args(NerfUpdate),
        help="fine-tune the original NeRF or retrain it (default: auto: retrain for proxies, "
        "fine-tune for boxes)")
  offer(how, "--second_iteration", action="store_true", default=None,
        help="run steps 4-7 once more from the edited NeRF")
  how.add_argument("--strict", action="store_true", default=None,
                   help="a prompt word the model does not know is an error, not a warning")
  offer(how, "--lpips", help="VGG-LPIPS weights (safetensors) for the fine-tuning loss "
        "(default: none, L1 only)")
  offer(how, "--clip", help="CLIP checkpoint directory for the directional similarity "
        "(default: none, not measured)")
  offer(how, "--views_per_device", type=argument_type(UpdateConfig, "views_per_device"),
        help="views inpainted per device at once (default: "
        f"{UpdateConfig.views_per_device})")
  trainings = ("the original NeRF's training, when the edit trains it (no --run; saved for the "
               "later NeRF update too)" if command in ("preview", "update") else
               "each NeRF training of the edit (the original when the edit trains it, the "
               "fine-tune or retrain)")
  how.add_argument("--max_seconds", type=argument_type(TrainConfig, "max_seconds"),
                   help=f"time budget in seconds of {trainings}: it stops there, its "
                   "learning-rate schedule spanning the budget (default: none, TrainConfig.steps "
                   "steps); per run: <run>/TrainConfig.max_seconds")
  how.add_argument("--replay", metavar="EDIT",
                   help=f"train again, step for step, what the earlier edit EDIT trained: "
                   f"{trainings} is given the progress its counterpart's schedule had at each "
                   "step, so a time-budgeted edit repeats bit for bit (with EDIT's settings: "
                   "--gin_file EDIT/config.gin)")
  how.add_argument("--redo", action="append", default=[], metavar="STAGE",
                   help=redo_help(command))


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
  """--gin_file, --gin_param and --quiet, which every edit command and the demo take."""
  configs.add_gin_arguments(parser, "UpdateConfig.views_per_device = 8")
  parser.add_argument("--quiet", action="store_true", help="no progress bars")


def _absolute_path(value: str) -> str:
  return str(Path(value).resolve())


# flag -> (gin binding, how to turn the flag's value into the bound value).
_FLAG_BINDINGS = {
    "data": ("EditConfig.data", _absolute_path),
    "downscale": ("EditConfig.downscale", None),
    "run": ("EditConfig.original_run", _absolute_path),
    "replay": ("EditConfig.replay", _absolute_path),
    "prompt": ("EditConfig.prompt", None),
    "negative_prompt": ("EditConfig.negative_prompt", None),
    "seed": ("EditConfig.seed", None),
    "model": ("EditConfig.model", _absolute_path),
    "controlnet": ("EditConfig.controlnet", _absolute_path),
    "scheduler": ("EditConfig.scheduler_kind", None),
    "sheet": ("EditConfig.sheet", None),
    "nerf_update": ("EditConfig.nerf_update", None),
    "second_iteration": ("EditConfig.second_iteration", None),
    "strict": ("EditConfig.strict_prompt", None),
    "scale": ("SelectionConfig.scale", None),
    "rotation": ("SelectionConfig.rotation_degrees", None),
    "translation": ("SelectionConfig.translation", None),
    "on_ground": ("SelectionConfig.ground_position", None),
    "size": ("SelectionConfig.ground_size", None),
    "heading": ("SelectionConfig.heading_degrees", None),
    "up": ("SelectionConfig.up", None),
    "mesh_up": ("SelectionConfig.mesh_up", None),
    "lpips": ("FinetuneConfig.lpips_weights", _absolute_path),
    "clip": ("EvaluationConfig.clip_model", _absolute_path),
    "views_per_device": ("UpdateConfig.views_per_device", None),
}


def flag_bindings(args: argparse.Namespace) -> list[str]:
  """gin bindings for the flags that were given."""
  bindings = []
  for flag, (binding, convert) in _FLAG_BINDINGS.items():
    value = getattr(args, flag, None)
    if value is not None:
      bindings.append(f"{binding} = {gin_value(convert(value) if convert else value)}")
  if getattr(args, "max_seconds", None) is not None:
    bindings += [f"{run}/TrainConfig.max_seconds = {gin_value(args.max_seconds)}"
                 for run in TRAINING_RUNS]
  if getattr(args, "box", None) is not None:
    if getattr(args, "proxy", None) is not None:
      raise InputError("give either --box or --proxy", field="selection")
    bindings += ["SelectionConfig.kind = 'box'",
                 f"SelectionConfig.box_min = {gin_value(args.box[:3])}",
                 f"SelectionConfig.box_max = {gin_value(args.box[3:])}"]
  if getattr(args, "proxy", None) is not None:
    proxy = (args.proxy if args.proxy.startswith(PRIMITIVE_PREFIX)
             else str(Path(args.proxy).resolve()))
    bindings += ["SelectionConfig.kind = 'proxy'", f"SelectionConfig.proxy = {proxy!r}"]
  return bindings


def parse_edit_config(directory: str | Path, gin_files, bindings) -> None:
  """Parses the edit's saved config.gin (when it exists), then `gin_files`, then `bindings`."""
  saved = Path(directory) / configs.SAVED_CONFIG_NAME
  configs.parse_gin(([saved] if saved.is_file() else []) + list(gin_files), list(bindings))


def edit_settings() -> EditSettings:
  """The edit's settings from the current gin bindings (`configs.parse_gin` first), with what
  the bindings leave to the model filled in from it (the mask growth)."""
  edit, selection = configs.build(EditConfig), configs.build(SelectionConfig)
  if selection.dilation_radius is None:
    selection = dataclasses.replace(
        selection, dilation_radius=generation.recommended_mask_dilation(edit.model))
  return EditSettings(
      edit=edit, selection=selection,
      sheet=configs.build(SheetConfig), preview=configs.build(PreviewConfig),
      update=configs.build(UpdateConfig), finetune=configs.build(FinetuneConfig),
      evaluation=configs.build(EvaluationConfig),
      generation=tuple(configs.build(GenerationOptions, scope) for scope in GENERATION_SCOPES),
      training={run: configs.build(TrainConfig, run) for run in TRAINING_RUNS},
      capacity=configs.build(CapacityRules), placement=configs.build(ReferencePlacement),
      attention=configs.build(AttentionOptions),
      consistency=configs.build(ConsistencySettings),
      nerf_consistency=configs.build(NerfConsistencySettings), gin_config=gin.config_str())


def run_command(name: str, directory: str | Path, redo=(), progress: bool = True,
                log: Callable[[str], None] | None = None) -> stages.EditContext:
  """Runs the pipeline up to the command's stage with the current gin bindings (saved as
  `directory`/config.gin first, which later commands read back). Each stage's progress lines go
  to `log`; by default, prefixed `signerf NAME`, to stderr as the progress bars do: stdout holds
  only the command's result (for `signerf eval --edit`, one JSON line). A refused directory is
  named by --edit (`ownership.FLAGS`). On a CPU the stages that train a NeRF run in a process of
  their own (`training_process`)."""
  settings = edit_settings()
  if log is None:
    log = lambda line: print(f"signerf {name} {line}", file=sys.stderr, flush=True)
  with stages.claimed_edit(directory, settings):
    configs.save_gin_config(directory)
    return stages.run_edit(directory, settings, until=LAST_STAGE[name], redo=tuple(redo),
                           progress=progress, log=log,
                           run_training=training_process.training_runner())


def run_stages(name: str, args: argparse.Namespace, extra_bindings=()
               ) -> tuple[stages.EditContext, float]:
  """Parses the edit's gin (saved config, files, flags, parameters) and runs the command's
  stages. Returns the run and its wall time in seconds."""
  start = time.perf_counter()
  parse_edit_config(args.edit, args.gin_file, flag_bindings(args) + list(extra_bindings)
                    + list(args.gin_param))
  edit = run_command(name, args.edit, args.redo, progress=not args.quiet)
  return edit, time.perf_counter() - start


def run_evaluation(edit_directory: str | Path, gin_files=(), bindings=()) -> int:
  """`signerf eval --edit DIR`: evaluates the edit (running any unfinished stage first; with
  the edit's saved gin, then `gin_files` and `bindings`) and prints the metrics as one JSON line
  (the figures, video and metrics.json are in DIR/evaluation)."""
  parse_edit_config(edit_directory, gin_files, bindings)
  edit = run_command("eval", edit_directory)
  metrics_path = edit.directory.path("evaluation", "metrics.json")
  print(json.dumps(json.loads(metrics_path.read_text())))
  return 0
