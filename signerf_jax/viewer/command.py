"""`signerf view`: the trained NeRF, its cameras and the edit's selection in a browser.

    signerf view --run runs/scene --edit edits/cow       # then open the printed address
    signerf edit --out edits/cow                         # continues from what was saved

Move the selection with its handle (or type its position, size and heading in the panel, in
the dataset's own units), stand a proxy on the surface under it, preview candidate sheets with
a prompt, seed and ControlNet scale, pick one, re-roll tiles, and save: the selection and
settings go into EDIT/config.gin as gin bindings, which every edit command reads first.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from signerf_jax.editing.config import PRIMITIVE_PREFIX
from signerf_jax.validation import argument_type


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help="the trained NeRF (`signerf train`)")
  parser.add_argument("--edit", help="the edit directory the preview and save write to "
                      "(default: RUN_edit beside the run)")
  parser.add_argument("--proxy", default=PRIMITIVE_PREFIX + "box",
                      help="the proxy to start with when the edit has no selection yet: a mesh "
                      "file or primitive:<box, sphere, cylinder, capsule, cow>")
  parser.add_argument("--host", default="127.0.0.1",
                      help="address to serve on (0.0.0.0: every interface)")
  parser.add_argument("--port", type=argument_type(int), default=8080)


def run(args: argparse.Namespace) -> int:
  from signerf_jax.viewer import app  # pylint: disable=g-import-not-at-top  (imports viser, JAX)
  run_dir = Path(args.run)
  edit_dir = Path(args.edit) if args.edit else run_dir.parent / f"{run_dir.name}_edit"
  proxy = (args.proxy if args.proxy.startswith(PRIMITIVE_PREFIX)
           else str(Path(args.proxy).resolve()))
  viewer = app.Viewer(run_dir, edit_dir, proxy=proxy, host=args.host, port=args.port)
  print(f"signerf view: open {viewer.url} (edit directory {edit_dir}; Ctrl-C stops)",
        file=sys.stderr, flush=True)
  try:
    while True:
      time.sleep(1.0)
  except KeyboardInterrupt:
    viewer.close()
  return 0
