"""`signerf place`: stand a proxy on the surface under a pixel of a training view, or put a box
around what rectangles drawn in two training views see.

    signerf info --run runs/scene                                   # views, frame, a default size
    signerf place --run runs/scene --edit edits/cow --view 12 --pixel 140 96 --proxy cow.obj
    signerf place --run runs/scene --edit edits/vase --rectangle 3 40 60 90 120 \
        --rectangle 17 100 50 150 118                               # a box, triangulated
    signerf preview --edit edits/cow --prompt "a red cow"           # the placement is saved

The pixel's ray into the trained NeRF gives the point, a plane fitted to the surface around it
the up direction the proxy stands along (or `--up`, the scene's up, as the edit commands take
it), and the proxy's size is `--size` in the dataset's units or `--size_fraction` of the view's
height. The selection is written as gin bindings into EDIT/config.gin (which every edit command
reads first) and printed in the dataset's own units; EDIT/placement.png shows the (first) view
with the selection's silhouette, before any diffusion runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from signerf_jax import cli, configs, files, ownership
from signerf_jax.editing import place
from signerf_jax.editing.commands import (HEADING_HELP, MESH_UP_HELP, UP_HELP, gin_value,
                                          parse_edit_config)
from signerf_jax.editing.config import PRIMITIVE_PREFIX, SelectionConfig
from signerf_jax.errors import InputError
from signerf_jax.nerf import evaluate
from signerf_jax.nerf.commands import load_recorded_dataset
from signerf_jax.validation import OpenUnitInterval, argument_type

FIGURE_NAME = "placement.png"


def selection_bindings(selection: SelectionConfig) -> list[str]:
  """The gin bindings that place `selection` (`place.PLACEMENT_FIELDS`)."""
  return [f"SelectionConfig.{name} = {gin_value(getattr(selection, name))}"
          for name in place.PLACEMENT_FIELDS[selection.kind]]


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help="the trained NeRF (`signerf train`)")
  cli.add_output_argument(parser, "--edit", deprecated=("--out",), required=True,
                          help="the edit directory: the placement goes into EDIT/config.gin, on "
                          "top of the settings saved there")
  parser.add_argument("--view",
                      help="a training view: its index or image name (`signerf info` lists them)")
  parser.add_argument("--pixel", nargs=2, type=argument_type(float), metavar=("X", "Y"),
                      help="pixel of that view, as the run loads it")
  parser.add_argument("--proxy",
                      help="a mesh file or primitive:<box, sphere, cylinder, capsule, cow>")
  parser.add_argument("--rectangle", action="append", nargs=5, default=[],
                      metavar=("VIEW", "X0", "Y0", "X1", "Y1"),
                      help="instead a box: a rectangle around the object in a training view; "
                      "give two or more views")
  size = parser.add_mutually_exclusive_group()
  size.add_argument("--size", type=argument_type(SelectionConfig, "ground_size"),
                    help="the proxy's largest side in the dataset's units (default: as "
                    "--size_fraction gives it)")
  size.add_argument("--size_fraction", type=argument_type(OpenUnitInterval),
                    default=place.DEFAULT_SIZE_FRACTION,
                    help="the proxy's largest side as a fraction of the view's height at the "
                    "picked point (default: %(default)s)")
  parser.add_argument("--heading", type=argument_type(float), default=0.0, help=HEADING_HELP)
  parser.add_argument("--up", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                      help=f"{UP_HELP} (default: the surface's normal at the picked point)")
  parser.add_argument("--mesh_up", type=argument_type(float), nargs=3, metavar=("X", "Y", "Z"),
                      default=SelectionConfig.mesh_up,
                      help=f"{MESH_UP_HELP} (default: "
                      f"{' '.join(f'{value:g}' for value in SelectionConfig.mesh_up)}, +y as the "
                      "shared meshes)")


def view_index(view: str, names) -> int:
  """A view given as an index into the training views or as its image: the name the dataset
  lists ("./train/0002"), its file name or its stem, with or without a suffix ("0002.png")."""
  if view.isdigit():
    return int(view)
  matches = [index for index, name in enumerate(names)
             if os.path.normpath(name) == os.path.normpath(view)]
  if not matches:  # A file name or stem is enough where it is unique.
    wanted = {Path(view).name, Path(view).stem}
    matches = [index for index, name in enumerate(names)
               if wanted & {Path(name).name, Path(name).stem}]
  if len(matches) != 1:
    raise InputError(f"{'no' if not matches else 'more than one'} training view named {view!r}",
                     field="view")
  return matches[0]


def _rectangles(arguments, names) -> tuple[list[int], list[list[float]]]:
  """(views, [x0, y0, x1, y1] each) of the --rectangle flags."""
  views, rectangles = [], []
  for view, *corners in arguments:
    try:
      rectangles.append([float(value) for value in corners])
    except ValueError:
      raise InputError(f"corners must be numbers, got {corners}", field="rectangle") from None
    views.append(view_index(view, names))
  return views, rectangles


def run(args: argparse.Namespace) -> int:
  pointing = args.pixel is not None or args.proxy is not None or args.view is not None
  if pointing == bool(args.rectangle) or (pointing and None in (args.view, args.pixel,
                                                                  args.proxy)):
    raise InputError("give --view, --pixel and --proxy (a proxy on a surface), or --rectangle "
                     "twice or more (a box)", field="place")
  trained = evaluate.load_run(args.run)
  dataset = load_recorded_dataset(trained.description, "train")
  inputs = (("run", args.run), ("data", dataset.root))
  ownership.check_claimable(args.edit, ownership.EDIT, inputs=inputs, flag="edit")  # Before work.
  if args.rectangle:
    views, rectangles = _rectangles(args.rectangle, dataset.image_names)
    selection, view, pixel = place.box_selection(dataset, views, rectangles), views[0], None
    report = (f"box {selection.box_min} .. {selection.box_max} where the views "
              f"{', '.join(map(str, views))} meet")
  else:
    view = view_index(args.view, dataset.image_names)
    found = place.locate(trained.model, trained.variables, dataset, view, tuple(args.pixel),
                         size=args.size, size_fraction=args.size_fraction)
    proxy = (args.proxy if args.proxy.startswith(PRIMITIVE_PREFIX)
             else str(Path(args.proxy).resolve()))
    selection, pixel = found.selection(proxy, args.heading, tuple(args.mesh_up)), found.pixel
    if args.up is not None:  # Standing along the scene's up rather than the surface's normal.
      selection = dataclasses.replace(selection, up=tuple(args.up))
    report = (f"view {view} ({dataset.image_names[view]}), pixel ({pixel[0]:g}, {pixel[1]:g}): "
              f"the surface there is {100 * found.plane.inlier_fraction:.0f}% planar around the "
              f"point (residual {found.plane.rms_distance:.2g} scene units)")
  figure = place.placement_figure(dataset, view, selection, pixel)
  bindings = selection_bindings(selection)
  bindings.append(f"EditConfig.original_run = {gin_value(str(Path(args.run).resolve()))}")
  parse_edit_config(args.edit, (), bindings)  # On top of the edit's saved settings, if any.
  out = Path(args.edit)
  with ownership.claimed(out, ownership.EDIT, inputs=inputs, flag="edit"):
    configs.save_gin_config(out)
    files.write_image(out / FIGURE_NAME, figure)
  print(f"signerf place: {report}; {out / FIGURE_NAME} shows it", file=sys.stderr)
  print(json.dumps({"selection": {name: getattr(selection, name)
                                  for name in place.PLACEMENT_FIELDS[selection.kind]},
                    "units": "the dataset's own", "bindings": bindings,
                    "config": str(out / configs.SAVED_CONFIG_NAME)}))
  return 0
