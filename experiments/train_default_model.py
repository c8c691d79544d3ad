"""Trains the default model (resumably, within a CPU budget), exports and verifies its weights.

    python experiments/train_default_model.py --data outputs/default_model_data \
        --run outputs/default_model_run --max_minutes 60 \
        [--gin_file default_model] [--gin_param 'unet_stage.num_steps = 100' ...]

Each call resumes the stages in RUN (`signerf_jax.default_model.stages`: VAE, then UNet + text
encoder, then ControlNet; finished stages are skipped) and starts no new step after
--max_minutes, so the whole training spans as many calls as it needs. Then, unless --no_export:
  * exports the weights reached so far (the finished model once all stages are done) in diffusers
    layout to --weights (default: the package's shipped `signerf_jax/default_model/weights`);
  * verifies the export by loading it back through the component loaders and checking that
    every parameter equals the trained one rounded to the stored dtype;
  * writes default_model_training.json (+ .gin) into --results DIR (default outputs/experiments/),
    or --output JSON: per stage the steps done, wall time, final losses (mean of the last 50
    steps), parameter counts, sizes on disk, and the loss curves (means over windows of
    CURVE_WINDOW steps), and
    default_model_training.png beside it (the curves).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gin
import numpy as np
from flax import traverse_util

from signerf_jax import configs, files
from signerf_jax.default_model import export, model, stages, training, training_data

import machine  # experiments/machine.py (this script's directory is on sys.path)
import plotting  # experiments/plotting.py (this script's directory is on sys.path)
import results_dir

SHIPPED_WEIGHTS = Path(model.__file__).resolve().parent / "weights"
CURVE_WINDOW = 10
FINAL_WINDOW = 50
PLOTTED = {"vae": ("l1", "gradient_l1"), "unet": ("loss_sheets", "loss_singles"),
           "controlnet": ("loss_sheets", "loss_singles")}


def window_means(values: np.ndarray, window: int) -> list[float]:
  count = len(values) // window
  return values[:count * window].reshape(count, window).mean(1).tolist()


def verify_export(directory: Path, params: dict, dtype) -> dict[str, float]:
  """Max |loaded - trained (rounded to dtype)| per component; all must be 0."""
  loaded = export.load_checkpoint(directory)
  pairs = {"vae": loaded.vae_params, "unet": loaded.unet_params,
           "controlnet": loaded.controlnet_params, "text_encoder": loaded.text_encoder.params}
  differences = {}
  for name, loaded_params in pairs.items():
    trained = traverse_util.flatten_dict(params[name])
    restored = traverse_util.flatten_dict(loaded_params)
    if set(trained) != set(restored):
      raise RuntimeError(f"{name}: parameter names differ after export")
    differences[name] = max(float(np.max(np.abs(
        np.asarray(restored[path], np.float32)
        - np.asarray(trained[path]).astype(dtype).astype(np.float32)))) for path in trained)
  return differences


def plot_curves(histories: dict, path: Path) -> None:
  """One panel per stage: log10 of the windowed losses against steps."""
  panels = []
  for stage in stages.STAGES:
    history = histories.get(stage, {})
    series = []
    for name in ("loss",) + PLOTTED[stage]:
      means = np.asarray(window_means(history[name], CURVE_WINDOW)) if name in history else []
      if len(means) > 1:
        steps = CURVE_WINDOW * (np.arange(len(means)) + 1)
        series.append(plotting.Series(name, steps, np.log10(np.maximum(means, 1e-8)),
                                      dashed=True))
    if series:
      panels.append(plotting.line_chart(stage, series, "steps", "log10 loss", width=420,
                                        height=320, y_from_zero=False))
    else:
      panels.append(np.full((320, 420, 3), 255, np.uint8))
  plotting.write_panels(path, panels)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--data", required=True, help="the generated dataset (make_default_model_data)")
  parser.add_argument("--run", required=True, help="checkpoint directory of the training")
  parser.add_argument("--max_minutes", type=float, default=60.0,
                      help="no new training step starts after this many minutes")
  parser.add_argument("--checkpoint_minutes", type=float, default=5.0)
  parser.add_argument("--init_from", help="an exported model the stages start from (to continue "
                      "training without the run's checkpoints; give skipped stages 0 steps)")
  parser.add_argument("--init_components", nargs="+", choices=export.COMPONENTS,
                      default=list(export.COMPONENTS),
                      help="with --init_from: the components taken from it (the others start "
                      "from random parameters)")
  parser.add_argument("--weights", default=str(SHIPPED_WEIGHTS), help="export directory")
  parser.add_argument("--no_export", action="store_true")
  configs.add_gin_arguments(parser)
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/default_model_training.json)")
  args = parser.parse_args(argv)
  start, measured_on = time.monotonic(), machine.record()
  configs.parse_gin(args.gin_file or ["default_model"], args.gin_param)
  data = training_data.load_split(args.data, "train")
  budget = training.RunBudget(deadline=start + 60 * args.max_minutes,
                              checkpoint_seconds=60 * args.checkpoint_minutes)
  initial = None
  if args.init_from:
    initial = {name: params for name, params in export.initial_params(args.init_from).items()
               if name in args.init_components}
  trained = stages.train(args.run, data, model.Architecture(), budget, initial=initial)
  configs.save_gin_config(args.run)

  result = {"machine": measured_on, "data": args.data, "run": args.run,
            "init_from": args.init_from,
            "complete": trained.complete,
            "wall_seconds_this_call": time.monotonic() - start, "stages": {}}
  for stage, history in trained.histories.items():
    result["stages"][stage] = {
        "steps": trained.steps[stage], "finished": trained.finished[stage],
        "wall_seconds": trained.wall_seconds[stage],
        "final_losses": {name: float(np.mean(values[-FINAL_WINDOW:]))
                         for name, values in history.items() if len(values)},
        "curves": {name: window_means(values, CURVE_WINDOW) for name, values in history.items()},
        "curve_window_steps": CURVE_WINDOW}
  result["total_training_wall_seconds"] = sum(
      stage["wall_seconds"] for stage in result["stages"].values())
  result["vae_scaling_factor"] = trained.architecture.vae_scaling_factor
  # A UNet exists once its stage has begun or when it came with --init_from.
  has_unet = trained.steps.get("unet", 0) > 0 or "unet" in (initial or {})
  if not args.no_export and has_unet:
    dtype = np.float16
    sizes = export.write_checkpoint(args.weights, trained.architecture, trained.params,
                                    data.tokenizer, dtype)
    result["export"] = {
        "directory": args.weights, "dtype": np.dtype(dtype).name, "bytes": sizes,
        "parameters": {name: model.parameter_count(params)
                       for name, params in trained.params.items()},
        "max_abs_difference_after_loading": verify_export(Path(args.weights), trained.params,
                                                          dtype)}
  output = Path(args.output or args.results / "default_model_training.json")
  files.write_json(output, result)
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  plot_curves(trained.histories, output.with_suffix(".png"))
  status = ", ".join(f"{stage} {steps} steps" for stage, steps in trained.steps.items())
  print(f"default model: {'complete' if trained.complete else 'in progress'} ({status}); "
        f"results in {output}" + (f", weights in {args.weights}" if "export" in result else ""))
  return 0


if __name__ == "__main__":
  sys.exit(main())
