"""`signerf view`: the trained NeRF, its cameras and the edit's selection in a browser.

    signerf view --run runs/scene --edit edits/cow       # then open the printed address
    signerf edit --edit edits/cow                        # continues from what was saved

Move the selection with its handle (or type its position, size and heading in the panel, in
the dataset's own units), stand a proxy on the surface under it, preview candidate sheets with
a prompt, seed and ControlNet scale, pick one, re-roll tiles, and save: the selection and
settings go into EDIT/config.gin as gin bindings, which every edit command reads first.

The printed address carries a token (http://127.0.0.1:8080/?token=...), as Jupyter's does: the
page and its websocket refuse requests without it, and the websocket refuses any page but the
viewer's own (`viewer.access`), so no other web page open in the browser can drive the viewer.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from signerf_jax.editing.config import PRIMITIVE_PREFIX
from signerf_jax.validation import argument_type
from signerf_jax.viewer import access


def add_arguments(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--run", required=True, help="the trained NeRF (`signerf train`)")
  parser.add_argument("--edit", help="the edit directory the preview and save write to, as "
                      "`signerf place`, `preview` and `edit` take it (default: RUN_edit beside "
                      "the run)")
  parser.add_argument("--proxy", default=PRIMITIVE_PREFIX + "box",
                      help="the proxy to start with when the edit has no selection yet: a mesh "
                      "file or primitive:<box, sphere, cylinder, capsule, cow>")
  parser.add_argument("--host", default="127.0.0.1",
                      help="address to serve on (default: %(default)s, this machine only; "
                      "0.0.0.0: every interface, so any machine that can reach this one can "
                      "connect, with the printed token)")
  parser.add_argument("--port", type=argument_type(int), default=8080,
                      help="port to serve on, or the next free one when it is taken (0: one the "
                      "system picks); the printed address names it")


def run(args: argparse.Namespace) -> int:
  from signerf_jax.viewer import app  # pylint: disable=g-import-not-at-top  (imports viser, JAX)
  run_dir = Path(args.run)
  edit_dir = Path(args.edit) if args.edit else run_dir.parent / f"{run_dir.name}_edit"
  proxy = (args.proxy if args.proxy.startswith(PRIMITIVE_PREFIX)
           else str(Path(args.proxy).resolve()))
  viewer = app.Viewer(run_dir, edit_dir, proxy=proxy, host=args.host, port=args.port)
  print(announcement(viewer.url, args.host, viewer.server.get_port(), edit_dir),
        file=sys.stderr, flush=True)
  try:
    wait_for_interrupt()
  except KeyboardInterrupt:
    viewer.close()
  return 0


def announcement(url: str, host: str, port: int, edit_dir: Path) -> str:
  """What `signerf view` prints when it serves: the address to open, with its token, and, for a
  host other machines can reach, a plain warning that they can."""
  lines = [f"signerf view: open {url} (edit directory {edit_dir}; Ctrl-C stops)"]
  if not access.is_loopback(host):
    where = ("every network interface of this machine" if host in access.WILDCARD_HOSTS
             else f"{host}, an address other machines can reach")
    lines.append(f"signerf view: serving on {where} (--host {host}): any machine that can reach "
                 f"this one on port {port} can connect, with the token in the address above; "
                 "from another machine, open it with this machine's name or address in place "
                 "of the host. Keep the token secret; --host 127.0.0.1 serves this machine only.")
  return "\n".join(lines)


def wait_for_interrupt() -> None:
  """Sleeps until Ctrl-C (KeyboardInterrupt): the viewer serves from threads of its own."""
  while True:
    time.sleep(1.0)
