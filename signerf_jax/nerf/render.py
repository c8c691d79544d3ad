"""Rendering whole images from a trained model: chunked (bounded memory, one compiled shape),
plus camera paths and writing colour / depth / video files."""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import os
from pathlib import Path
from typing import Iterator

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera, files
from signerf_jax.errors import InputError
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import front_to_back, ray_samples, render_state, render_trained, sampling

# Outputs copied back per pixel (weights stay on device: they are per sample).
IMAGE_OUTPUTS = ("rgb", "accumulation", "depth", "median_depth", "distance", "near_weight",
                 "selection_weight")
# A box nothing is inside (its low corner above its high one): no selection weight.
NO_BOX = np.array([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]], np.float32)

# Rays rendered at once by default (`--chunk_size`). A chunk is never padded beyond this or the
# rays there are: one compiled shape serves every smaller ray count (masks of any size), and a
# chunk size above the ray count allocates no more than those rays.
DEFAULT_CHUNK_SIZE = 4096
# How trained fields render unless a caller asks otherwise (`front_to_back`).
DEFAULT = front_to_back.RenderSettings()
# How held-out metrics render: every field sample, so that a reported PSNR is the model's as
# trained and not its faster approximation's (the other shortcuts change a render by about
# their thresholds, at most 1e-2 of a pixel's colour, and its PSNR by at most 0.003 dB on lego
# and stitch: docs/results.md).
HELD_OUT = dataclasses.replace(DEFAULT, field_sample_fraction=1.0)
# Chunks rendered at once, each from a thread of its own: rendering front to back runs many
# small operations one after another, which leave a CPU's other cores idle (two chunks at once
# rendered 1.25x the rays per second of one on an idle 2-core CPU); a GPU or TPU overlaps one
# chunk's copies with another's work.
CHUNKS_IN_FLIGHT = 2
# Bytes each ray of a chunk holds at the least, whatever the model: the padded rays on the host
# and on the device (origins and directions, 3 float32 each, the cosine, the camera index), and
# the outputs on the device and copied back (rgb's 3 float32 and 6 more). The samples along the
# rays take far more, on the device.
CHUNK_BYTES_PER_RAY = 2 * (3 + 3 + 1 + 1) * 4 + 2 * (3 + len(IMAGE_OUTPUTS) - 1) * 4


@functools.partial(jax.jit, static_argnums=(0, 6, 7))
def _render_chunk(model: nerf_model.NerfModel, variables, chunk: camera.Rays, near_distance,
                  selection_box, march_box, march_steps, settings, skipping):
  """Renders one chunk of rays [C] (one compilation per chunk size, march_steps and settings,
  whatever the image size; march_box and march_steps: `ray_samples.render_march`, or None;
  settings: `front_to_back.RenderSettings`, or None for every sample; skipping:
  `render_state.skipping`, or {} without settings).

  "near_weight" is the render weight of the samples nearer to the camera than `near_distance`
  (scene units, traced): what near-camera floaters contribute. "selection_weight" is the weight
  of the samples whose centres lie inside `selection_box` ([2, 3] low and high corners, scene
  units, traced): the opacity of what the NeRF holds there, as this camera sees it.
  """
  march = None if march_steps is None else ray_samples.OccupiedMarch(march_box, march_steps)
  if settings is not None:
    outputs = render_trained.render_rays(model, variables, chunk, settings, skipping,
                                        near_distance, selection_box, march)
    return {name: outputs[name] for name in IMAGE_OUTPUTS}
  outputs, _ = nerf_model.render_rays(model, variables, chunk, jax.random.PRNGKey(0),
                                      training=False, occupied_march=march)
  outputs.update(front_to_back.weight_statistics(
      outputs["weights"], sampling.midpoints(outputs["edges"]), chunk, near_distance,
      selection_box))
  return {name: outputs[name] for name in IMAGE_OUTPUTS}


def _occupied_march(model: nerf_model.NerfModel, variables):
  """The occupancy sampler's short march, or None (`render_state.occupied_march`)."""
  return render_state.occupied_march(model, variables)


@jax.jit
def _one_camera_rays(one_camera: camera.Cameras, camera_index, subpixel) -> camera.Rays:
  rays = camera.image_rays(one_camera, 0, subpixel)
  return rays.replace(camera_indices=jnp.full(rays.shape, camera_index, jnp.int32))


def image_rays(cameras: camera.Cameras, camera_index: int, subpixel=(0.5, 0.5)) -> camera.Rays:
  """`camera.image_rays`, compiled (eagerly, undistortion's loop would recompile at every call)
  once per image size: the camera is taken out of `cameras` on the host first, so that sets
  of cameras of other sizes (every stage's) share one program."""
  one_camera = jax.tree.map(lambda array: np.asarray(array)[[camera_index]], cameras)
  return _one_camera_rays(one_camera, np.int32(camera_index), np.asarray(subpixel, np.float32))


def physical_memory() -> int | None:
  """This machine's memory in bytes (None where the system does not say)."""
  try:
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
  except (AttributeError, OSError, ValueError):
    return None


def _size_text(size: float) -> str:
  """`size` bytes in binary units: "109.1 TiB"."""
  for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
    if size < 1024 or unit == "PiB":
      return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
    size /= 1024
  raise AssertionError("unreachable")


def _check_positive(value, field: str) -> None:
  if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
    raise InputError(f"must be a positive integer, got {value!r}", field=field)


def check_chunk_size(chunk_size: int, field: str = "chunk_size",
                     memory: int | None = None) -> None:
  """Refuses a chunk size that is not a positive integer or whose buffers cannot fit in this
  machine's memory (`memory` bytes; default `physical_memory`), before anything is allocated:
  numpy would otherwise fail on its first chunk with "Unable to allocate 109. TiB".

  Raises:
    InputError naming `field` (a command passes its flag, "--chunk_size"), the value, the
    memory it would need at the least (`CHUNK_BYTES_PER_RAY`) and the memory there is.
  """
  _check_positive(chunk_size, field)
  memory = physical_memory() if memory is None else memory
  needed = int(chunk_size) * CHUNK_BYTES_PER_RAY
  if memory is not None and needed > memory:
    raise InputError(
        f"{chunk_size} rays at once need at least {_size_text(needed)} of memory "
        f"({CHUNK_BYTES_PER_RAY} bytes a ray for the rays and their outputs alone), more than "
        f"this machine's {_size_text(memory)}; the default is {DEFAULT_CHUNK_SIZE}",
        field=field)


def render_chunks(model: nerf_model.NerfModel, variables, rays: camera.Rays,
                  chunk_size: int = DEFAULT_CHUNK_SIZE, near_distance: float = 0.0,
                  selection_box=None, settings: front_to_back.RenderSettings | None = DEFAULT
                  ) -> Iterator[dict[str, np.ndarray]]:
  """Renders flat rays [R] chunk by chunk, yielding each chunk's outputs as numpy arrays [C]
  (the last chunk padded by repeating the last ray, and cut back): a caller that stops
  iterating stops the work (but the chunks in flight, `CHUNKS_IN_FLIGHT`), as the viewer does
  when its camera moves. A chunk holds at most
  max(R, DEFAULT_CHUNK_SIZE) rays whatever `chunk_size`. See `render_rays_chunked` for the
  arguments and outputs.

  Raises:
    InputError: `chunk_size` is not a positive integer.
  """
  count = rays.shape[0]
  _check_positive(chunk_size, "chunk_size")
  chunk_size = min(int(chunk_size), max(count, DEFAULT_CHUNK_SIZE))
  rays = jax.device_get(rays)  # Sliced on the host: no compilation per chunk position.
  near_distance = jnp.float32(near_distance)
  box = jnp.asarray(NO_BOX if selection_box is None else selection_box, jnp.float32)
  # An edit region's model renders the rays that miss its region as its original does.
  fast_model, fast_variables = ((model, variables) if model.edit_region is None or
                                settings is None else (model.original, variables["original"]))
  march = _occupied_march(fast_model, fast_variables)
  march_box, march_steps = (None, None) if march is None else march
  skipping = {} if settings is None else render_state.skipping(fast_model, fast_variables)
  variables = render_state.on_device(model, variables)

  def render(start: int) -> dict[str, np.ndarray]:
    chunk, size = _padded_chunk(rays, start, chunk_size)
    outputs = jax.device_get(_render_chunk(model, variables, chunk, near_distance, box,
                                           march_box, march_steps, settings, skipping))
    return {name: value[:size] for name, value in outputs.items()}

  yield from _in_flight(render, range(0, count, chunk_size))


def _padded_chunk(rays: camera.Rays, start: int, chunk_size: int) -> tuple[camera.Rays, int]:
  """Host rays [R] from `start`, `chunk_size` of them (padded by repeating the last ray), and
  how many are real."""
  stop = min(start + chunk_size, rays.shape[0])
  return jax.tree.map(lambda a: np.concatenate(
      [a[start:stop], np.repeat(a[stop - 1:stop], start + chunk_size - stop, 0)]), rays), (
          stop - start)


@functools.partial(jax.jit, static_argnums=0)
def _crosses_region(model: nerf_model.NerfModel, chunk: camera.Rays):
  return nerf_model.crosses_region(model, chunk)


def crossing_rays(model: nerf_model.NerfModel, rays: camera.Rays) -> np.ndarray:
  """[R] bool: which of the flat rays [R] cross `model`'s edit region (the only rays an edit
  region's field changes), DEFAULT_CHUNK_SIZE at a time (one compilation)."""
  rays = jax.device_get(rays)
  pieces = []
  for start in range(0, rays.shape[0], DEFAULT_CHUNK_SIZE):
    chunk, size = _padded_chunk(rays, start, DEFAULT_CHUNK_SIZE)
    pieces.append(np.asarray(_crosses_region(model, chunk))[:size])
  return np.concatenate(pieces)


def _render_edited_rays(model: nerf_model.NerfModel, variables, rays: camera.Rays,
                        chunk_size: int, near_distance: float, selection_box,
                        settings: front_to_back.RenderSettings) -> dict[str, np.ndarray]:
  """`render_rays_chunked` of an edit region's model on flat rays [R]: the rays that miss the
  region rendered by its original (the program the original's own renders use, so compiled
  once for both), those that cross it with every sample. What `render_trained.render_rays`
  does within one chunk's program, which compiles the original's renderer into it again."""
  rays = jax.device_get(rays)
  crossing = crossing_rays(model, rays)
  parts = ((~crossing, model.original, variables["original"], settings),
           (crossing, model, variables, None))
  outputs: dict[str, np.ndarray] = {}
  for selected, part_model, part_variables, part_settings in parts:
    if not selected.any():
      continue
    subset = jax.tree.map(lambda array, selected=selected: array[selected], rays)
    rendered = assemble(render_chunks(part_model, part_variables, subset, chunk_size,
                                      near_distance, selection_box, part_settings),
                        subset.shape)
    for name, value in rendered.items():
      outputs.setdefault(name, np.zeros(rays.shape + value.shape[1:], value.dtype))[
          selected] = value
  return outputs


def _in_flight(render, starts) -> Iterator[dict[str, np.ndarray]]:
  """render(start) for each of `starts`, in order, CHUNKS_IN_FLIGHT at a time in threads of
  their own; a caller that stops iterating cancels those not begun."""
  pool = concurrent.futures.ThreadPoolExecutor(CHUNKS_IN_FLIGHT)
  pending: collections.deque = collections.deque()
  try:
    for start in starts:
      pending.append(pool.submit(render, start))
      if len(pending) == CHUNKS_IN_FLIGHT:
        yield pending.popleft().result()
    while pending:
      yield pending.popleft().result()
  finally:
    pool.shutdown(wait=False, cancel_futures=True)


def render_rays_chunked(model: nerf_model.NerfModel, variables, rays: camera.Rays,
                        chunk_size: int = DEFAULT_CHUNK_SIZE, near_distance: float = 0.0,
                        selection_box=None,
                        settings: front_to_back.RenderSettings | None = DEFAULT
                        ) -> dict[str, np.ndarray]:
  """Renders any number of rays in fixed-size chunks (the last one padded), so memory stays
  bounded and every chunk reuses one compiled function.

  Args:
    rays: Rays of any shape [...].
    near_distance: scene units; "near_weight" is the weight nearer to the camera than this.
    selection_box: [2, 3] low and high corners (scene units) of the box whose render weight is
      "selection_weight"; None for none.
    settings: how the field is evaluated (`front_to_back.RenderSettings`; default `DEFAULT`);
      None: every sample, as training renders (an edit region's model renders the rays that
      cross its region so whatever the settings).
  Returns:
    numpy arrays: rgb [..., 3], accumulation, depth, median_depth, distance, near_weight,
    selection_weight [...].
  """
  flat = rays.reshape(-1)
  if model.edit_region is not None and settings is not None and flat.shape[0]:
    outputs = _render_edited_rays(model, variables, flat, chunk_size, near_distance,
                                  selection_box, settings)
    return {name: value.reshape(rays.shape + value.shape[1:]) for name, value in outputs.items()}
  return assemble(render_chunks(model, variables, flat, chunk_size, near_distance,
                                selection_box, settings), rays.shape)


def assemble(pieces, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
  """The outputs of `render_chunks`' chunks (an iterable of dicts of [C, ...] arrays) as arrays
  of the rays' `shape` [...]."""
  pieces = list(pieces)
  return {name: np.concatenate([piece[name] for piece in pieces]).reshape(
      shape + pieces[0][name].shape[1:]) for name in pieces[0]}


def render_cameras(model: nerf_model.NerfModel, variables, cameras: camera.Cameras,
                   chunk_size: int = DEFAULT_CHUNK_SIZE, near_distance: float = 0.0,
                   selection_box=None, pixels=None, supersampling: int | None = None,
                   settings: front_to_back.RenderSettings | None = DEFAULT
                   ) -> dict[str, np.ndarray]:
  """Renders every camera, or only the pixels `pixels` of each.

  Args:
    pixels: None (every pixel), or [N, H, W] bool: render only these rays, all cameras' in one
      stream of chunks; every output is 0 at the other pixels. A measurement inside masks then
      costs only the masks' rays (an edit's fit: a small share of the pixels, many times
      faster).
    supersampling: each output pixel is the mean of supersampling^2 rays through a regular
      grid of points inside it (`camera.subpixel_positions`), as a photo's pixel is the mean of
      the light over its area (anti-aliasing; supersampling^2 times the work); 1: the centre
      ray; None: the model's `Capacity.pixel_samples` (how it was trained).
    (the others: see `render_rays_chunked`)
  Returns:
    rgb [N, H, W, 3] in [0, 1]; accumulation [N, H, W]; depth, median_depth [N, H, W] z-depth and
    distance [N, H, W] ray distance, in scene units (the far bound where nothing was hit);
    near_weight [N, H, W], the weight nearer than `near_distance` to the camera;
    selection_weight [N, H, W], the weight inside `selection_box` (see `render_rays_chunked`).
    With supersampling, each is the mean over a pixel's rays.
  Raises:
    InputError: `pixels` is not [N, H, W] for these cameras, or `supersampling` or
      `chunk_size` is not a positive integer.
  """
  _check_positive(chunk_size, "chunk_size")
  if supersampling is None:
    supersampling = model.capacity.pixel_samples
  if isinstance(supersampling, bool) or not isinstance(supersampling, (int, np.integer)) or (
      supersampling < 1):
    raise InputError(f"must be a positive integer, got {supersampling!r}", field="supersampling")
  positions = camera.subpixel_positions(supersampling)
  shape = (cameras.num_cameras, cameras.height, cameras.width)
  if pixels is None:
    pixels = np.ones(shape, bool)
  elif np.shape(pixels) != shape:
    raise InputError(f"pixels of shape {np.shape(pixels)} for cameras needing {shape}",
                     field="pixels")
  pixels = np.asarray(pixels, bool)
  outputs = {name: np.zeros(shape + ((3,) if name == "rgb" else ()), np.float32)
             for name in IMAGE_OUTPUTS}
  if not pixels.any():
    return outputs
  for position in positions:
    views = [jax.tree.map(lambda array, inside=pixels[index]: np.asarray(array)[inside],
                          image_rays(cameras, index, position))
             for index in range(cameras.num_cameras) if pixels[index].any()]
    rays = jax.tree.map(lambda *parts: np.concatenate(parts), *views)
    rendered = render_rays_chunked(model, variables, rays, chunk_size, near_distance,
                                   selection_box, settings)
    for name in IMAGE_OUTPUTS:
      outputs[name][pixels] += rendered[name] / len(positions)
  return outputs


class _CodecUnavailable(Exception):
  pass


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: int = 24) -> Path:
  """Writes RGB frames [T, H, W, 3] in [0, 1] as an mp4 (mp4v); if this OpenCV build has no mp4
  encoder, as a Motion-JPEG .avi next to it. Written atomically; returns the path written."""
  frames = np.round(np.clip(np.asarray(frames), 0, 1) * 255).astype(np.uint8)
  height, width = frames.shape[1:3]
  for suffix, codec in ((".mp4", "mp4v"), (".avi", "MJPG")):
    target = Path(path).with_suffix(suffix)
    try:
      with files.atomic_path(target) as temporary:
        writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*codec), fps,
                                 (width, height))
        if not writer.isOpened():
          raise _CodecUnavailable(codec)
        for frame in frames:
          writer.write(frame[..., ::-1])
        writer.release()
      return target
    except _CodecUnavailable:
      continue
  raise OSError(f"OpenCV can write neither mp4 nor avi video here ({path})")


def depth_image(depth: np.ndarray, near: float | None = None, far: float | None = None
                ) -> np.ndarray:
  """A z-depth map [H, W] as a colour image [H, W, 3] in [0, 1] (turbo colour map over inverse
  depth, so near structure and the distant background both stay visible).

  Args:
    near, far: depth range of the colour map; default the 1st and 99th percentiles of `depth`.
  """
  depth = np.maximum(np.asarray(depth, np.float32), 1e-6)
  near = float(np.percentile(depth, 1)) if near is None else near
  far = float(np.percentile(depth, 99)) if far is None else far
  inverse = (1 / depth - 1 / max(far, near * (1 + 1e-6))) / max(1 / near - 1 / far, 1e-12)
  levels = np.round(np.clip(1 - inverse, 0, 1) * 255).astype(np.uint8)
  return cv2.applyColorMap(levels, cv2.COLORMAP_TURBO)[..., ::-1].astype(np.float32) / 255


def write_renders(directory: str | os.PathLike, names, outputs: dict[str, np.ndarray]) -> None:
  """Writes per view: <name>.png (colour), <name>.depth.exr (median z-depth, scene units),
  <name>.depth.png (that depth as a picture, `depth_image`), <name>.accumulation.png.

  Median depth (where the accumulated weight reaches one half), not the expected depth: in an
  unbounded scene a percent of weight left on the last interval, reaching hundreds of scene
  units away, dominates the expected depth and hides the surfaces.
  """
  directory = Path(directory)
  for index, name in enumerate(names):
    stem = Path(name).with_suffix("").as_posix().replace("/", "_").lstrip("._")
    depth = outputs["median_depth"][index]
    files.write_image(directory / f"{stem}.png", outputs["rgb"][index])
    files.write_exr(directory / f"{stem}.depth.exr", depth)
    files.write_image(directory / f"{stem}.depth.png", depth_image(depth))
    files.write_image(directory / f"{stem}.accumulation.png", outputs["accumulation"][index])
