"""The edit's `signerf` subcommands (shared flags and helpers here): `edit` runs the whole
pipeline; `preview`, `update` and `finetune` run it up to their stage (earlier stages run first
if needed, finished ones are skipped); `eval --edit` evaluates. This is where gin meets the
editing code: `edit_settings` builds the `EditSettings` every stage reads from the bindings.

The flags describing the edit (--data, --prompt, --box / --proxy, --model, ...) are shorthand for
gin bindings of `editing.config` and are needed only when the edit directory is created: they
are saved in OUT/config.gin, which every later command reads first (flags given again override
it, and every stage whose settings changed runs again).

    signerf preview --out edits/cow --data scenes/field --prompt "a red cow" \\
        --proxy cow.obj --on_ground 0.1 -0.3 0 --size 0.5      # candidate sheets, seeds 0-3
    signerf preview --out edits/cow --reroll 2/1,4@7            # sheet 2, tiles 1 and 4 again
    signerf edit --out edits/cow --sheet 2/1,4@7                 # the rest, with that sheet
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

from signerf_jax import configs
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.editing import generation, stages
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


def gin_value(value) -> str:
  """A Python value as a gin literal (strings, numbers, booleans, tuples)."""
  if isinstance(value, list):
    value = tuple(value)
  return repr(value)


def add_edit_arguments(parser: argparse.ArgumentParser) -> None:
  """The flags shared by edit, preview, update and finetune."""
  parser.add_argument("--out", required=True, help="the edit directory (created or resumed)")
  data = parser.add_argument_group("inputs (saved in OUT/config.gin)")
  data.add_argument("--data", help="dataset directory (nerfstudio, Blender, LLFF)")
  data.add_argument("--downscale", type=argument_type(EditConfig, "downscale"),
                    help="integer image downscale of the dataset")
  data.add_argument("--run", help="an already trained NeRF of the dataset (`signerf train`); "
                    "without it the edit trains one")
  data.add_argument("--prompt", help="what the edited region should show")
  data.add_argument("--negative_prompt", help="what it should not show")
  data.add_argument("--seed", type=argument_type(EditConfig, "seed"),
                    help="seed of the image set update (and default sheet)")
  data.add_argument("--model", help="diffusers ControlNet inpainting pipeline directory, e.g. "
                    "SD 1.5 inpainting (default: the shipped model)")
  data.add_argument("--controlnet", help="diffusers ControlNet directory (depth or inpaint), "
                    "replacing the pipeline's")
  data.add_argument("--scheduler", choices=typing.get_args(SchedulerOverride)[1:],
                    help="override the checkpoint's scheduler")
  where = parser.add_argument_group(
      "selection (the dataset's own world units unless SelectionConfig.frame)")
  where.add_argument("--box", type=argument_type(float), nargs=6,
                     metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                     help="shape selection: axis-aligned box min and max corners")
  where.add_argument("--proxy", help="proxy selection: a mesh file or primitive:<box, sphere, "
                     "cylinder, capsule, cow>")
  where.add_argument("--scale", type=argument_type(SelectionConfig, "scale"),
                     help="proxy similarity transform: scale")
  where.add_argument("--rotation", type=argument_type(float), nargs=3, metavar=("RX", "RY", "RZ"),
                     help="proxy similarity transform: Euler angles in degrees (x, y, z)")
  where.add_argument("--translation", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help="proxy similarity transform: translation")
  where.add_argument("--on_ground", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help="instead stand the proxy upright with its footprint centred here")
  where.add_argument("--size", type=argument_type(SelectionConfig, "ground_size"),
                     help="with --on_ground: the proxy's largest side")
  where.add_argument("--heading", type=argument_type(float),
                     help="with --on_ground: turn about up (degrees)")
  where.add_argument("--up", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                     help="the up direction (default: the cameras' mean up)")
  how = parser.add_argument_group("how")
  how.add_argument("--sheet", help="the sheet recipe to propagate: SEED or SEED/TILE,TILE@SEED")
  how.add_argument("--nerf_update", choices=typing.get_args(NerfUpdate),
                   help="fine-tune the original NeRF or retrain (auto: retrain for proxies)")
  how.add_argument("--second_iteration", action="store_true", default=None,
                   help="run steps 4-7 once more from the edited NeRF")
  how.add_argument("--strict", action="store_true", default=None,
                   help="a prompt word the model does not know is an error, not a warning")
  how.add_argument("--lpips", help="VGG-LPIPS weights (safetensors) for the fine-tuning loss")
  how.add_argument("--clip", help="CLIP checkpoint directory for the directional similarity")
  how.add_argument("--views_per_device", type=argument_type(UpdateConfig, "views_per_device"),
                   help="views inpainted per device at once")
  how.add_argument("--max_seconds", type=argument_type(TrainConfig, "max_seconds"),
                   help="time budget of each NeRF training of the edit (the original when the "
                   "edit trains it, the fine-tune or retrain): it stops there, its learning-rate "
                   "schedule spanning the budget; per run: <run>/TrainConfig.max_seconds")
  how.add_argument("--redo", action="append", default=[], metavar="STAGE",
                   help="run this stage (and those after it) again; repeatable")
  add_common_arguments(parser)


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
  only the command's result (for `signerf eval --edit`, one JSON line)."""
  settings = edit_settings()
  if log is None:
    log = lambda line: print(f"signerf {name} {line}", file=sys.stderr, flush=True)
  with stages.claimed_edit(directory, settings):
    configs.save_gin_config(directory)
    return stages.run_edit(directory, settings, until=LAST_STAGE[name], redo=tuple(redo),
                           progress=progress, log=log)


def run_stages(name: str, args: argparse.Namespace, extra_bindings=()
               ) -> tuple[stages.EditContext, float]:
  """Parses the edit's gin (saved config, files, flags, parameters) and runs the command's
  stages. Returns the run and its wall time in seconds."""
  start = time.perf_counter()
  parse_edit_config(args.out, args.gin_file, flag_bindings(args) + list(extra_bindings)
                    + list(args.gin_param))
  edit = run_command(name, args.out, args.redo, progress=not args.quiet)
  return edit, time.perf_counter() - start


def run_evaluation(edit_directory: str | Path) -> int:
  """`signerf eval --edit DIR`: evaluates the edit (running any unfinished stage first) and
  prints the metrics as one JSON line (the figures, video and metrics.json are in
  DIR/evaluation)."""
  parse_edit_config(edit_directory, (), ())
  edit = run_command("eval", edit_directory)
  metrics_path = edit.directory.path("evaluation", "metrics.json")
  print(json.dumps(json.loads(metrics_path.read_text())))
  return 0
