"""Progressive rendering for the viewer: the newest view a browser asks for, coarse first and
finer while its camera rests, in a thread of its own so that rendering never blocks the page.

A frame in progress is abandoned between two chunks of rays as soon as a newer view is asked
for, so a moving camera gets a coarse frame after at most one chunk's delay; frames before the
finest also take fewer of the field's samples (`MOVING_SAMPLE_FRACTION`).
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import threading
import time
from typing import Callable, Iterator

import numpy as np

from signerf_jax.nerf import render
from signerf_jax.viewer.cameras import ViewPose, cameras_for_pose

# Frame heights in pixels, coarse to fine: the coarsest answers a moved camera within about a
# second even on a small CPU, the finer ones follow (docs/performance.md).
HEIGHTS = (64, 128, 256)
CHUNK_SIZE = 4096
# Frames before the finest, what a moving camera sees, render this fraction of the radiance
# field's samples (proposal sampler, `Capacity.render_sample_fraction`); the finest renders as
# `render.render_chunks` does by default (front to back, `render.DEFAULT`: two thirds at
# most). A third keeps a moving camera's frames of a real capture interactive on a 2-core CPU
# (stitch's 128-px frame: 0.36 s, docs/results.md) for a modest loss of quality.
MOVING_SAMPLE_FRACTION = 1 / 3


@dataclasses.dataclass(frozen=True)
class Frame:
  """A rendered view.

  Attributes:
    rgb: [H, W, 3] float32 in [0, 1].
    depth: [H, W] float32 z-depth (distance along the camera axis), scene units; the far bound
      where the NeRF holds nothing.
    seconds: time since the view was asked for.
  """

  rgb: np.ndarray
  depth: np.ndarray
  seconds: float

  @property
  def height(self) -> int:
    return self.rgb.shape[0]


def render_progressively(model, variables, pose: ViewPose, is_current: Callable[[], bool],
                         heights=HEIGHTS, chunk_size: int = CHUNK_SIZE) -> Iterator[Frame]:
  """Frames of `pose` at each of `heights`, stopping as soon as `is_current()` is False
  (checked after every chunk of rays)."""
  start = time.perf_counter()
  moving_model = _with_fewer_samples(model)
  for height in heights:
    cameras = cameras_for_pose(pose, height)
    rays = render.image_rays(cameras, 0)
    pieces = []
    frame_model = model if height == heights[-1] else moving_model
    for piece in render.render_chunks(frame_model, variables, rays.reshape(-1), chunk_size):
      if not is_current():
        return
      pieces.append(piece)
    image = render.assemble(pieces, rays.shape)
    yield Frame(image["rgb"], image["depth"], time.perf_counter() - start)


def _with_fewer_samples(model):
  """`model` rendering `MOVING_SAMPLE_FRACTION` of its field's samples; itself when it renders
  fewer already or has no proposal sampler (a changed model would only compile again)."""
  capacity = model.capacity
  if capacity.sampler != "proposal" or capacity.render_sample_fraction <= MOVING_SAMPLE_FRACTION:
    return model
  return dataclasses.replace(model, capacity=dataclasses.replace(
      capacity, render_sample_fraction=MOVING_SAMPLE_FRACTION))


class ProgressiveRenderer:
  """A thread that renders the newest requested pose (`request`) with `frames(pose,
  is_current)` and hands every frame to `show`, until `close`."""

  def __init__(self, frames: Callable[[ViewPose, Callable[[], bool]], Iterator[Frame]],
               show: Callable[[Frame], None]):
    self._frames, self._show = frames, show
    self._condition = threading.Condition()
    self._pose: ViewPose | None = None
    self._version = 0
    self._closed = False
    self._thread = threading.Thread(target=self._run, name="signerf-view-render", daemon=True)
    self._thread.start()

  def request(self, pose: ViewPose) -> None:
    """Renders `pose` next, abandoning any older one."""
    with self._condition:
      self._pose, self._version = pose, self._version + 1
      self._condition.notify()

  def close(self) -> None:
    with self._condition:
      self._closed = True
      self._condition.notify()
    self._thread.join()

  def _is_current(self, version: int) -> bool:
    return not self._closed and self._version == version

  def _has_news(self, version: int) -> bool:
    """Closed, or a pose newer than `version` was asked for."""
    return self._closed or self._version != version

  def _run(self) -> None:
    version = 0
    while True:
      with self._condition:
        self._condition.wait_for(functools.partial(self._has_news, version))
        if self._closed:
          return
        pose, version = self._pose, self._version
      is_current = functools.partial(self._is_current, version)
      try:
        for frame in self._frames(pose, is_current):
          if not is_current():  # A newer view was asked for while this frame was made.
            break
          self._show(frame)
      except Exception as error:  # pylint: disable=broad-except  (the thread must keep serving)
        print(f"signerf view: rendering failed: {error!r}", file=sys.stderr)
