"""What the evaluation generates from: the held-out samples as inpainting inputs, and the calls.

`ViewInputs` holds the eval split's samples as the pipeline takes them (the object-free view, the
box mask, the control depth, the caption) with the truth to compare with; `select_samples` picks
the single views and the sheets whose caption names no colour. Every generation has its own key
(`evaluation_key`: seed, purpose, sample and view), so a sample's generations do not depend on
batch sizes or on what else is evaluated. `generate_with_captions` inpaints samples with one
caption each in fixed-size batches, timed by `CallTimer`; `round_trip` is the VAE round trip
the generated objects are segmented against (`generated_objects`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import parallel
from signerf_jax.default_model import batches
from signerf_jax.default_model import evaluation
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import sampler
from signerf_jax.editing.generation import Generator
from signerf_jax.errors import InputError
from signerf_jax.geometry import masks as masks_lib

KEY_PURPOSES = ("single", "sheet", "independent", "slot", "shape_transfer")


def evaluation_key(seed: int, purpose: str, sample_index: int, view_index: int = 0) -> np.ndarray:
  """[2] uint32 key data of one generation: a `KEY_PURPOSES` entry, sample and view."""
  key = jax.random.PRNGKey(seed)
  for number in (KEY_PURPOSES.index(purpose), sample_index, view_index):
    key = jax.random.fold_in(key, number)
  return np.asarray(key)


@dataclasses.dataclass(frozen=True)
class ViewInputs:
  """Per-view inputs of eval samples, [S, V, ...] (float32 unless said).

  Attributes:
    background: [S, V, H, W, 3] the object-free views in [0, 1] (what is inpainted).
    masks: [S, V, H, W] the box inpainting masks.
    controls: [S, V, H, W] normalised control depth of the views with the object.
    silhouettes: [S, V, H, W] bool, the true object silhouettes.
    truth: [S, V, H, W, 3] the true renders with the object in [0, 1].
    view_kinds: [S, V] indices into `samples.VIEW_KINDS`.
    captions: [S] captions.
  """

  background: np.ndarray
  masks: np.ndarray
  controls: np.ndarray
  silhouettes: np.ndarray
  truth: np.ndarray
  view_kinds: np.ndarray
  captions: list[str]

  @classmethod
  def from_arrays(cls, arrays: dict[str, np.ndarray], indices) -> "ViewInputs":
    """The samples `indices` of a loaded split's sheets or singles (`training_data.load_split`
    with keep=None)."""
    chosen = {name: arrays[name][np.asarray(indices, np.int64)]
              for name in ("rgb", "background_rgb", "depth", "control_near_far", "silhouette",
                           "boxes", "view_kinds", "caption")}
    height, width = chosen["silhouette"].shape[-2:]
    return cls(background=chosen["background_rgb"].astype(np.float32) / 255.0,
               masks=batches.box_masks(chosen["boxes"], height, width),
               controls=np.asarray(batches.control(chosen)),
               silhouettes=chosen["silhouette"] > 0,
               truth=chosen["rgb"].astype(np.float32) / 255.0,
               view_kinds=chosen["view_kinds"],
               captions=[str(text) for text in chosen["caption"]])


def select_samples(singles: dict[str, np.ndarray], sheets: dict[str, np.ndarray],
                   settings: evaluation.EvaluationSettings) -> tuple[np.ndarray, np.ndarray]:
  """(indices of the single views, indices of the sheets whose caption names no colour)."""
  available = len(singles["caption"])
  if settings.num_singles > available:
    raise InputError(f"asked for {settings.num_singles} single views, the split has {available}",
                     field="default_model_evaluation.num_singles")
  uncoloured = np.flatnonzero(~np.asarray(sheets["names_color"], bool))
  if not len(uncoloured):
    raise InputError("no sheet caption leaves the colour out: consistency cannot be measured",
                     field="names_color")
  return np.arange(settings.num_singles), uncoloured[:settings.num_sheets]


@jax.jit
def vae_round_trip(models: sampler.DiffusionModels, images: jax.Array) -> jax.Array:
  """[N, H, W, 3] images in [0, 1] encoded (posterior mode) and decoded, one at a time."""
  vae = models.vae

  def one(image):
    posterior = vae.apply({"params": models.vae_params}, image[None] * 2.0 - 1.0,
                          method=vae.encode)
    return vae.apply({"params": models.vae_params}, posterior.mode(), method=vae.decode)[0]

  return jnp.clip(jax.lax.map(one, images) * 0.5 + 0.5, 0.0, 1.0)


def round_trip(generator: Generator, images: np.ndarray) -> np.ndarray:
  """`vae_round_trip` of [..., H, W, 3] images, keeping the leading axes."""
  flat = np.asarray(images, np.float32).reshape((-1,) + images.shape[-3:])
  return np.asarray(vae_round_trip(generator.pipeline.models, flat)).reshape(images.shape)


class CallTimer:
  """Wall time of generation calls per task, telling apart the first call of each compiled
  program (an input shape with a batch size: `Generator` calls with equal ones share one
  compiled sampler), which includes the compilation."""

  def __init__(self):
    self.calls: dict[str, list[tuple[float, int, bool]]] = {}
    self._programs: set[tuple] = set()

  def time(self, task: str, input_shape: tuple, batch_size: int, function: Callable, *args):
    """Runs `function(*args)`, a call generating a batch of `batch_size` samples of
    `input_shape` (a partial batch is padded to it), and records its wall time."""
    start = time.perf_counter()
    result = function(*args)
    seconds = time.perf_counter() - start
    program = (tuple(input_shape), batch_size)
    self.calls.setdefault(task, []).append((seconds, batch_size, program not in self._programs))
    self._programs.add(program)
    return result

  def summary(self) -> dict[str, dict]:
    """Per task: calls, batch size, the median time of the calls that compiled nothing and that
    per sample of the batch, and the program's first call with the compilation in it
    (compile_seconds = first call - steady median; None without steady calls)."""
    result = {}
    for task, calls in self.calls.items():
      steady = [seconds for seconds, _, first in calls if not first]
      batch_size = calls[0][1]
      median = float(np.median(steady)) if steady else None
      entry = {"calls": len(calls), "batch_size": batch_size, "steady_call_seconds": median,
               "seconds_per_sample": None if median is None else median / batch_size}
      first = [seconds for seconds, _, is_first in calls if is_first]
      if first:
        entry["first_call_seconds"] = first[0]
        entry["compile_seconds"] = None if median is None else first[0] - median
      result[task] = entry
    return result


def generate_with_captions(generator: Generator, captions: Sequence[str], image, mask, control,
                           keys, timer: CallTimer, task: str) -> np.ndarray:
  """Inpaints N samples, each with its own caption, in calls of `generator.batch_size`.

  Args:
    image: [N, H, W, 3]; mask, control: [N, H, W] or [N, H, W, 1]; keys: [N, 2] key data.
  Returns:
    [N, H, W, 3] float32 in [0, 1].
  """
  with_channels = lambda array: np.asarray(array, np.float32).reshape(np.shape(image)[:3] + (-1,))
  image, mask, control = with_channels(image), with_channels(mask), with_channels(control)
  outputs = []
  for start in range(0, len(captions), generator.batch_size):
    part = slice(start, start + generator.batch_size)
    texts = list(captions[part])
    count = len(texts)
    # Always batch_size prompt rows (the last repeated): one prompt shape, one compiled program.
    texts += texts[-1:] * (generator.batch_size - count)
    prompt = parallel.replicate(pipeline_lib.encode_prompts(generator.pipeline, texts),
                                generator.mesh)
    outputs.append(timer.time(task, image.shape[1:], generator.batch_size,
                              dataclasses.replace(generator, prompt=prompt),
                              image[part], mask[part], control[part], keys[part]))
  return np.concatenate(outputs)


def pipeline_proxy_masks(silhouettes: np.ndarray, settings: evaluation.EvaluationSettings
                         ) -> np.ndarray:
  """[..., H, W] float32: the pipeline's proxy masks of true silhouettes [..., H, W] (dilated and
  feathered as `SelectionConfig` does by default)."""
  return np.asarray(masks_lib.dilate_and_feather(silhouettes, radius=settings.proxy_mask_dilation,
                                                 feather=settings.proxy_mask_feather))


def with_scale(generator: Generator, scale: float) -> Generator:
  """The generator at another ControlNet scale (traced: no recompilation)."""
  return dataclasses.replace(generator, options=dataclasses.replace(
      generator.options, controlnet_conditioning_scale=float(scale)))
