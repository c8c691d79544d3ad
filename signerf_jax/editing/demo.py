"""`signerf demo`: the whole method on a fresh machine, with the shipped model.

1. a synthetic scene is generated (`data.synthetic`, the demo's camera rig), unless OUT/scene
   already holds it;
2. the primitive cow proxy (`geometry.primitives`) is stood on the scene's reserved free spot
   (scene.json `free_spot`);
3. `signerf edit` runs in OUT/edit with the prompt: original NeRF, selection, reference sheet
   (candidates side by side), image set update, edited dataset, NeRF update, evaluation.
The scene and the proxy come from the repository alone (gin_configs/demo.gin reads no mesh
files), so every machine makes the same demo, with or without ../shared/data. Budgets (NeRF
seconds, diffusion steps, views) are in gin_configs/demo.gin; every stage shows
progress and the run ends with one line naming the before/after renders, the sheet, the video
and the metrics. Rerunning resumes: finished stages are skipped.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Annotated, Any

from signerf_jax import cli, configs, files, ownership, validation
from signerf_jax.data import synthetic, synthetic_render
from signerf_jax.editing import commands
from signerf_jax.editing.config import DEFAULT_MODEL_DIR, PRIMITIVE_PREFIX
from signerf_jax.errors import InputError
from signerf_jax.validation import NonNegativeInt, Range

PROXY = f"{PRIMITIVE_PREFIX}cow"


@dataclasses.dataclass(frozen=True)
class DemoSettings(validation.CheckedFields):
  """The demo's scene and edit (gin: `demo.<field>`).

  Attributes:
    prompt: what to insert.
    scene_seed: seed of the synthetic scene.
    cow_size_fraction: the cow's length as a fraction of the free spot's diameter.
    heading_degrees: the cow's heading about the up axis.
  """

  prompt: str = "a red cow"
  scene_seed: NonNegativeInt = 0
  cow_size_fraction: Annotated[float, Range(0, 1, low_inclusive=False)] = 0.9
  heading_degrees: float = 30.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
  cli.add_output_argument(parser, "--out", default="outputs/demo",
                          help="output directory: new or empty, or an earlier demo's (resumed); "
                          "writes scene/ (the synthetic scene) and edit/ (the edit) there")
  parser.add_argument("--prompt", help="what to insert (default: demo.prompt, 'a red cow')")
  parser.add_argument("--model", help="a diffusers ControlNet inpainting pipeline directory "
                      "(default: the shipped model)")
  commands.add_common_arguments(parser)


def model_directory(model: str | None) -> str:
  """The given diffusers pipeline directory (absolute), or the shipped model's."""
  model = str(Path(model).resolve()) if model else str(DEFAULT_MODEL_DIR)
  if not Path(model).is_dir():
    raise InputError("diffusion model directory not found (without --model: the shipped "
                     "model, not installed here)", model, "model")
  return model


def ensure_scene(directory: Path, seed: int) -> dict[str, Any]:
  """The scene.json of the synthetic scene in `directory`, generated first unless it is there
  (with the gin-bound `synthetic_scene` settings and `synthetic_cameras` rig, whose bindings
  are saved beside it)."""
  if not (directory / synthetic_render.SCENE_FILE_NAME).is_file():
    dataset, _ = synthetic_render.generate(directory, seed=seed,
                                           settings=configs.build(synthetic.SceneSettings),
                                           rig=configs.build(synthetic_render.CameraRig))
    configs.save_gin_config(directory)
    print(f"signerf demo: synthetic scene of {dataset.num_images} views "
          f"({dataset.width}x{dataset.height} px) written to {directory}", flush=True)
  return files.read_json(directory / synthetic_render.SCENE_FILE_NAME)


def edit_bindings(scene_dir: Path, scene: dict[str, Any], settings: DemoSettings, prompt: str,
                  model: str) -> list[str]:
  """gin bindings of the demo's edit: the scene, prompt and model, and the cow proxy stood on
  the scene's reserved free spot."""
  free_spot = scene["free_spot"]
  return [
      f"EditConfig.data = {str(scene_dir.resolve())!r}", f"EditConfig.prompt = {prompt!r}",
      f"EditConfig.model = {model!r}", "SelectionConfig.kind = 'proxy'",
      f"SelectionConfig.proxy = {PROXY!r}",
      f"SelectionConfig.ground_position = {tuple(free_spot['center'])!r}",
      f"SelectionConfig.ground_size = {2 * free_spot['radius'] * settings.cow_size_fraction!r}",
      f"SelectionConfig.heading_degrees = {settings.heading_degrees!r}",
      f"SelectionConfig.up = {tuple(scene['up'])!r}",
  ]


def run(args: argparse.Namespace) -> int:
  start = time.perf_counter()
  out = Path(args.out)
  gin_files = ["demo", *args.gin_file]
  configs.parse_gin(gin_files, args.gin_param)
  settings = configs.build(DemoSettings)
  model = model_directory(args.model)
  scene_dir = out / "scene"
  with ownership.claimed(out, ownership.DEMO):
    scene = ensure_scene(scene_dir, settings.scene_seed)
    prompt = args.prompt or settings.prompt
    bindings = edit_bindings(scene_dir, scene, settings, prompt, model)
    configs.parse_gin(gin_files, bindings + list(args.gin_param))
    edit = commands.run_command("demo", out / "edit", progress=not args.quiet)
  evaluation = edit.directory.path("evaluation")
  metrics = files.read_json(evaluation / "metrics.json")
  video = [path for path in (evaluation / "before_after.mp4", evaluation / "before_after.avi")
           if path.is_file()]
  print(f"signerf demo: '{prompt}' inserted in {time.perf_counter() - start:.0f} s; "
        f"before/after {evaluation / 'before_after.png'}, sheet {evaluation / 'sheet.png'}, "
        f"candidates {edit.directory.path('preview', 'preview.png')}"
        + (f", video {video[0]}" if video else "")
        + f", metrics {evaluation / 'metrics.json'} (background PSNR "
        f"{metrics['background']['psnr_paper']:.1f} dB)")
  return 0
