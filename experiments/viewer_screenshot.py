"""What `signerf view` shows, as a picture: the viewer served for a run (and edit) and opened in a
headless Chromium, photographed once the finest frame has arrived.

  python experiments/viewer_screenshot.py --run RUN --edit EDIT [--view 0] [--name viewer]

Needs the test extras (selenium) and Debian's chromium and chromium-driver packages. Writes
NAME.png into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import shutil
import time

from signerf_jax import files
from signerf_jax.viewer import app

import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)

WINDOW = (1280, 760)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--run", required=True)
  parser.add_argument("--edit", required=True)
  parser.add_argument("--view", type=int, default=0, help="the dataset view to look through")
  parser.add_argument("--name", default="viewer")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  from selenium import webdriver  # pylint: disable=g-import-not-at-top  (a test extra)
  from selenium.webdriver.chrome.service import Service  # pylint: disable=g-import-not-at-top
  viewer = app.Viewer(args.run, args.edit, port=8099)
  options = webdriver.ChromeOptions()
  options.binary_location = shutil.which("chromium")
  for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                   f"--window-size={WINDOW[0]},{WINDOW[1]}", "--use-angle=swiftshader",
                   "--enable-unsafe-swiftshader", "--force-device-scale-factor=1"):
    options.add_argument(argument)
  browser = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
  try:
    browser.get(viewer.url)
    while not viewer.server.get_clients():
      time.sleep(0.2)
    client = next(iter(viewer.server.get_clients().values()))
    viewer.jump_to_view(client, args.view)
    time.sleep(1.0)  # The browser's camera follows; frames of the old view stop.
    viewer.shown_frames.pop(client.client_id, None)
    while (frame := viewer.shown_frames.get(client.client_id)) is None or (
        frame.height < max(viewer.heights)):
      time.sleep(0.2)
    time.sleep(2.0)  # The browser draws the last frame.
    args.results.mkdir(parents=True, exist_ok=True)
    path = args.results / f"{args.name}.png"
    files.write_bytes(path, browser.get_screenshot_as_png())
    print(f"{path}: view {args.view}, finest frame after {frame.seconds:.1f} s")
  finally:
    browser.quit()
    viewer.close()


if __name__ == "__main__":
  main()
