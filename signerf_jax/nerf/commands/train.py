"""`signerf train`: train (or resume) a NeRF on a dataset, then evaluate it on its held-out
views. The run directory gets the gin bindings as config.gin, which a resume reads back.
`--replay RUN` trains again what RUN trained, given the progress its schedule had at each step
(`training_run.read_schedule`): a time-budgeted run, repeated bit for bit."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from signerf_jax import checkpoints, cli, configs, ownership
from signerf_jax.data import frame as frame_lib
from signerf_jax.data import load_dataset, load_views
from signerf_jax.nerf import capacity, occupancy, train, training_run
from signerf_jax.errors import InputError
from signerf_jax.nerf.commands import (DataConfig, add_data_arguments, data_options,
                                       load_recorded_dataset)
from signerf_jax.nerf.commands import evaluate as evaluate_command
from signerf_jax.validation import argument_type

# What --replay takes from the run it repeats, so none of these may be given with it.
REPLAYED_FLAGS = ("data", "steps", "max_seconds", "downscale", "eval_every",
                  "held_out", "scene_kind", "scene_center", "scene_radius", "gin_file",
                  "gin_param")


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--data", default=None,
                      help=f"{cli.DATA_HELP}; required unless --replay")
  cli.add_output_argument(
      parser, "--run", deprecated=("--out",), required=True,
      help="run directory: new or empty (a run starts), or a run of `signerf train` (it "
      "resumes); writes config.gin, model.json, checkpoint.msgpack, eval.json and eval/ there")
  parser.add_argument("--steps", type=argument_type(train.TrainConfig, "steps"), default=None,
                      help="training steps (default: the gin-bound TrainConfig.steps, "
                      f"{train.TrainConfig.steps})")
  parser.add_argument("--max_seconds", type=argument_type(train.TrainConfig, "max_seconds"),
                      default=None,
                      help="training time budget in seconds: training stops there and the "
                      "schedule spans it (resumable; default: the gin-bound "
                      "TrainConfig.max_seconds, none)")
  parser.add_argument("--replay", default=None, metavar="RUN",
                      help="train again what the run RUN trained: its data, settings and model, "
                      "given the progress its schedule had at each step (RUN/schedule.json), so "
                      "a time-budgeted run repeats bit for bit on the same kind of machine")
  parser.add_argument("--skip_eval", action="store_true",
                      help="do not evaluate on the held-out views after training")
  parser.add_argument("--start_over", action="store_true",
                      help="train afresh in a run directory that holds a run, replacing the "
                      "files that run wrote (others stay); without it a run is resumed, and only "
                      "on the data it was trained on")
  add_data_arguments(parser)
  configs.add_gin_arguments(parser)


def run(args: argparse.Namespace) -> int:
  if args.replay is not None:
    return _replay(args)
  if args.data is None:
    raise InputError("give the dataset to train on (or --replay RUN)", field="data")
  run_dir = Path(args.run)
  ownership.check_claimable(run_dir, ownership.RUN, inputs=(("data", args.data),), flag="run")
  resuming = checkpoints.has_checkpoint(run_dir) and not args.start_over
  saved_config = run_dir / configs.SAVED_CONFIG_NAME
  gin_files = args.gin_file
  # Resuming without new gin files continues with the run's own configuration.
  if not gin_files and resuming and saved_config.is_file():
    gin_files = [saved_config]
  configs.parse_gin(gin_files, args.gin_param)
  # Every setting is built (and so checked) before any work starts.
  options = data_options(args, configs.build(DataConfig))
  config, rules = configs.build(train.TrainConfig), configs.build(capacity.CapacityRules)
  loading = {name: value for name, value in options.items() if name != "root"}
  loading["held_out"] = tuple(loading["held_out"])
  dataset = load_dataset(options["root"], split="train", **loading)
  if not args.skip_eval:  # The held-out views are checked before the training, not after it.
    load_views(options["root"], split="eval", **loading)
  if resuming:
    training_run.check_resumable(run_dir, dataset, options)
  model = (training_run.read_model_file(run_dir)[0] if resuming
           else training_run.build_model(dataset, rules=rules))
  return _train_and_evaluate(args, dataset, model, config, options)


def _replay(args: argparse.Namespace) -> int:
  """`signerf train --replay RUN --run RUN2`: RUN's data, gin bindings, model and recorded
  schedule (see the module docstring)."""
  source = Path(args.replay)
  ownership.check_claimable(args.run, ownership.RUN, inputs=(("replay", source),), flag="run")
  given = [name for name in REPLAYED_FLAGS if getattr(args, name, None) not in (None, False, [])]
  if given:
    raise InputError(f"--replay repeats the run with its own data and settings: leave out "
                     f"--{given[0]}", source, "replay")
  progress = training_run.read_schedule(source)
  saved_config = source / configs.SAVED_CONFIG_NAME
  if progress is None or not saved_config.is_file():
    missing = training_run.SCHEDULE_FILE if progress is None else configs.SAVED_CONFIG_NAME
    raise InputError(f"has no {missing}: not a run of `signerf train`, or trained before runs "
                     "recorded their schedule", source, "replay")
  configs.parse_gin([saved_config], [])
  model, description = training_run.read_model_file(source)
  dataset = load_recorded_dataset(description, "train")
  changes = training_run.data_changes(source, dataset, description.get("data_options"))
  if changes:
    raise InputError(f"its data changed since it was trained ({'; '.join(changes)}): it cannot "
                     "be repeated", source, "replay")
  return _train_and_evaluate(args, dataset, model, configs.build(train.TrainConfig),
                             description["data_options"], progress)


def _train_and_evaluate(args: argparse.Namespace, dataset, model, config, options,
                        replay_progress=None) -> int:
  """Trains in args.run (claimed; a run there resumes), then evaluates unless --skip_eval."""
  run_dir = Path(args.run)
  inputs = (("data", options["root"]), ("replay", args.replay))
  print(f"signerf train: {dataset.num_images} training views of {dataset.width}x"
        f"{dataset.height} px; {frame_lib.summary_line(dataset.frame)}\n"
        f"signerf train: {capacity.describe(model.capacity)}", file=sys.stderr)
  with ownership.claimed(run_dir, ownership.RUN, inputs=inputs, flag="run"):
    if args.start_over:
      ownership.remove_written(run_dir)
    configs.save_gin_config(run_dir)
    trainer = training_run.train(dataset, run_dir, steps=args.steps, max_seconds=args.max_seconds,
                                 model=model, config=config, data_options=options,
                                 replay_progress=replay_progress)
    statistics = trainer.last_statistics
    message = (f"signerf train: {trainer.step} steps, {trainer.seconds_trained:.0f} s trained, "
               f"last batch {statistics.get('psnr', float('nan')):.2f} dB")
    if trainer.data.keypoints is not None:
      message += (f", depth at {trainer.data.keypoints.count} triangulated keypoint "
                  "observations (a sparse capture)")
    if trainer.data.neighbour_views is not None:
      message += (f", colours compared with the "
                  f"{trainer.data.neighbour_views.shape[1]} nearest views")
    grid = trainer.state.variables.get("occupancy")
    carved = 0.0 if grid is None else float(np.mean(np.asarray(grid) == occupancy.CARVED))
    if carved:
      message += (f", {carved:.0%} of the scene box outside the photos' visual hull (empty by "
                  "their alpha)")
    if not args.skip_eval:
      report = evaluate_command.evaluate_run(run_dir)
      message += (f"; held-out {report['held_out']['psnr']:.2f} dB / SSIM "
                  f"{report['held_out']['ssim']:.3f} on {report['held_out']['num_views']} views, "
                  f"gap to training views {report['generalisation_gap_db']:.2f} dB "
                  f"({run_dir / evaluate_command.EVAL_FILE}, renders in "
                  f"{run_dir / evaluate_command.RENDERS_FOLDER})")
  print(f"{message}; run in {run_dir}")
  return 0
