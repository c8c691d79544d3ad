"""How much the preview's candidate sheets differ from seed to seed, prompt by prompt.

    python experiments/measure_preview_seeds.py [--edit outputs/real_scene_edit/edit]
        [--prompts "a teddy bear" "a red teddy bear"] [--seeds 0 1 2 3] [--out DIR]

The preview offers one candidate sheet per seed so that the user can pick one (issue 18). For
each prompt this runs `signerf preview` as a user does, on a copy of a placed edit
(experiments/real_scene_edit.py's teddy bear on the real capture stitch, by default), and
measures the candidates against each other: the mean absolute RGB difference of every pair of
candidates inside the inpainting mask and outside it (the pasted-back renders), and the palette
colour each candidate gives the object (the dominant colour of its tiles' pixels on the proxy's
visible silhouette, as the edit's prompt-colour evaluation takes it).
Writes preview_seeds.json and preview_seeds.png (each prompt's candidates) into --results DIR
(default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import collections
import itertools
import os
import sys
from pathlib import Path

import numpy as np

from signerf_jax import files, ownership
from signerf_jax.default_model import generated_objects
from signerf_jax.editing import figures, sheet

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position
from real_scene_edit import signerf  # pylint: disable=wrong-import-position


def pairwise_difference(candidates: np.ndarray, where: np.ndarray) -> dict[str, float]:
  """Mean absolute RGB difference over `where` of every pair of candidates [N, H, W, 3]
  (`where` [H, W] bool): the mean and the smallest over the pairs."""
  differences = [float(np.abs(candidates[i] - candidates[j])[where].mean())
                 for i, j in itertools.combinations(range(len(candidates)), 2)]
  return {"mean": float(np.mean(differences)), "min": float(np.min(differences))}


def tile_colors(candidate: np.ndarray, selected: np.ndarray, layout: sheet.SheetLayout
                ) -> list[str]:
  """The dominant palette colour of each tile's pixels on the proxy's silhouette
  (candidate [SH, SW, 3]; selected [M, h, w] bool), for the tiles that show the proxy."""
  tiles, _ = sheet.disassemble(candidate, layout)
  names, _ = generated_objects.object_colors(np.asarray(tiles), selected)
  return [name for name in names if name is not None]


def measure(edit: Path, seeds: list[int]) -> dict:
  """The candidates of the preview in `edit` compared with each other."""
  reference = np.load(edit / "reference" / "inputs.npz")
  selected, masks = reference["selected"], reference["mask"]
  layout = sheet.SheetLayout(tile_height=selected.shape[1], tile_width=selected.shape[2])
  candidates = np.stack([np.load(edit / "preview" / "candidates" / f"{seed}.npz")["rgb"]
                         for seed in seeds])
  empty_slot = np.zeros(selected.shape[1:] + (1,), np.float32)
  inside = np.asarray(sheet.assemble(masks[..., None], empty_slot, layout, is_mask=True)
                      )[..., 0] >= 0.5
  per_tile = [tile_colors(candidate, selected, layout) for candidate in candidates]
  sheet_colors = [collections.Counter(names).most_common(1)[0][0] for names in per_tile]
  return {"difference_inside_mask": pairwise_difference(candidates, inside),
          "difference_outside_mask": pairwise_difference(candidates, ~inside),
          "tile_colors": dict(zip(map(str, seeds), per_tile)),
          "sheet_colors": dict(zip(map(str, seeds), sheet_colors)),
          "distinct_sheet_colors": len(set(sheet_colors))}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--edit", default="outputs/real_scene_edit/edit",
                      help="a placed edit (its config.gin: the trained NeRF and the selection)")
  parser.add_argument("--prompts", nargs="+", default=["a teddy bear", "a red teddy bear"])
  parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
  parser.add_argument("--out", default="outputs/preview_seeds")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  placed = Path(args.edit) / "config.gin"
  if not placed.is_file():
    raise SystemExit(f"{placed}: no placed edit here (run experiments/real_scene_edit.py)")
  record = machine.record()
  cache = Path(args.out) / "compilation_cache"
  results, images = {}, []
  for prompt in args.prompts:
    edit = Path(args.out) / prompt.replace(" ", "_")
    ownership.clear(edit, ownership.EDIT)
    seconds, _ = signerf(cache, "preview", "--edit", edit, "--gin_file", placed, "--prompt",
                         prompt, "--seeds", *args.seeds, "--quiet")
    results[prompt] = {**measure(edit, args.seeds), "preview_seconds": seconds}
    print(f"{prompt!r}: {results[prompt]}", flush=True)
    images.append(figures.image_grid([[files.read_image(edit / "preview" / "preview.png")]],
                                     [[f"--prompt '{prompt}'"]]))
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / "preview_seeds.json", {
      "what": "the preview's candidate sheets compared with each other, per prompt (mean "
              "absolute RGB difference of the pairs inside and outside the inpainting mask; "
              "the object's palette colour per candidate)",
      "edit": str(Path(args.edit).resolve()), "seeds": args.seeds, "prompts": results,
      "machine": {**record, "load_average_at_end": os.getloadavg()}})
  files.write_image(args.results / "preview_seeds.png", plotting.stacked(images))


if __name__ == "__main__":
  main()
