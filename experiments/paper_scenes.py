"""One scene of the paper's scene table (appendix, "Generation Information"), edited end to end.

    python experiments/paper_scenes.py --scene bear_grizzly --data DATA --model SDXL_PIPELINE \\
        [--controlnet DIR] --edit edits/bear_grizzly --box X0 Y0 Z0 X1 Y1 Z1 [--lpips WEIGHTS]
    python experiments/paper_scenes.py --scene field_cow --data DATA --model SD15_PIPELINE \\
        --controlnet DIR --edit edits/field_cow --proxy cow.obj --on_ground X Y Z --size S

runs `signerf edit` (every flag of it applies) with gin_configs/paper_scenes.gin (what all scenes
share: 30k NeRF steps and no time budget, the 2 x 3 sheet, 512 px tiles) and
gin_configs/paper_scenes/SCENE.gin (the table's denoising strength, ControlNet scale and guidance
per iteration, the second iteration, the prompt, box or proxy selection). The dataset, the model
and the selection are the user's: parsing fails, naming the binding, until they are given.
Rerunning resumes.

Writes into --results DIR (default outputs/experiments/) paper_scenes_SCENE.json (the machine
and the code's commit, the gin settings and every seed, the evaluation's metrics, the generation
settings of each iteration, the seconds of every stage), .gin (the edit's full configuration)
and .png (the before/after renders above the reference sheet).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gin

from signerf_jax import configs, files
from signerf_jax.editing import commands, figures
from signerf_jax.editing.commands import sweeps
from signerf_jax.editing.config import as_json
from signerf_jax.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

SCENE_DIR = configs.GIN_CONFIG_DIR / "paper_scenes"


def scene_names() -> list[str]:
  """The scenes with a gin file in gin_configs/paper_scenes/."""
  return sorted(path.stem for path in SCENE_DIR.glob("*.gin"))


def scene_gin_files(scene: str) -> list[str]:
  """The gin files of a scene, in parsing order."""
  return ["paper_scenes", f"paper_scenes/{scene}"]


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--scene", required=True, choices=scene_names(),
                      help="the row of the paper's scene table")
  results_dir.add_argument(parser)
  commands.add_edit_arguments(parser)
  args = parser.parse_args(argv)
  args.gin_file = scene_gin_files(args.scene) + args.gin_file
  measured_on = machine.record()
  try:
    edit, seconds = commands.run_stages("edit", args)
  except InputError as error:
    print(f"paper_scenes: error: {error}", file=sys.stderr)
    return 2
  final = 2 if edit.settings.edit.second_iteration else 1
  evaluation = edit.directory.path("evaluation")
  summary = sweeps.summarize_edit(edit)
  output = Path(args.results) / f"paper_scenes_{args.scene}.json"
  files.write_json(output, {
      "scene": args.scene, "machine": measured_on, "gin_files": args.gin_file,
      **machine.settings_record(gin.config_str(), edit=edit.settings),
      "seconds": seconds, **summary,
      "generation": {f"iteration_{iteration}": as_json(edit.generation_options(iteration))
                     for iteration in range(1, final + 1)},
      "metrics": files.read_json(evaluation / "metrics.json")})
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  sheet = files.read_image(evaluation / "sheet.png")[..., :3]
  files.write_image(output.with_suffix(".png"), plotting.stacked([
      files.read_image(evaluation / "before_after.png")[..., :3],
      figures.image_grid([[sheet]], [[f"reference sheet (iteration {final})"]])], gap=0))
  print(f"paper_scenes {args.scene}: done in {seconds:.0f} s, background PSNR "
        f"{summary['quality']['background_psnr']:.2f} dB -> {output}, "
        f"{output.with_suffix('.png')}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
