"""CLIP image preprocessing, bit-exact with transformers' PIL backend (and OpenAI's CLIP).

`CLIPImageProcessorPil` (transformers 5; the PIL path of the older `CLIPImageProcessor`) and
OpenAI's `clip.load(...)[1]` both:
  1. resize so that the shorter side is `shortest_edge` (224), the longer one
     int(shortest_edge * long / short), with Pillow's bicubic filter on the uint8 image;
  2. take the centre `crop_height` x `crop_width` crop (top = (H - crop) // 2);
  3. scale to [0, 1] and normalise with the CLIP mean and standard deviation.

Pillow's uint8 resampling is reproduced exactly here (`pil_bicubic_resize`): the separable
filter a = -0.5 whose support widens by the scale factor when shrinking (antialiasing), weights
normalised per output pixel and rounded to 22-bit fixed point, and two passes (horizontal then
vertical, or vertical first when the height shrinks by more than twice as many pixels as the
width, as Pillow 13 decides) whose intermediate result is rounded and clipped to uint8. The output
is identical to Pillow 13's `Image.resize(..., Image.BICUBIC)` (older Pillow always ran the
horizontal pass first: up to one grey level apart in the other case), so the normalised pixels
match transformers to float32 rounding (the tests check <= 1e-6).

transformers 5's default `CLIPImageProcessor` is the torchvision backend instead (it needs
torchvision, which this project cannot install next to the CPU torch it tests with): torch's
antialiased bicubic in float, rounded to uint8 once at the end. Measured against Pillow with
`torch.nn.functional.interpolate(..., mode="bicubic", antialias=True)` on random images, 3-25% of
the pixels differ, mostly by one grey level but by up to ~20 at sharp edges, where Pillow clips
the overshoot of its first pass to uint8. This module follows Pillow, i.e. the PIL backend and
OpenAI's reference preprocessing.

Float images in [0, 1] are first rounded to uint8 (as when renders are saved to PNG). transformers
would truncate them instead (`(x * 255).astype(uint8)`); pass uint8 images for a bit-exact
comparison with it.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Mapping

import numpy as np

from signerf_jax.errors import InputError

OPENAI_CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
PIL_BICUBIC = 3  # PIL.Image.Resampling.BICUBIC, the `resample` of CLIP preprocessor configs.
# Pillow's fixed-point precision for 8-bit resampling (Resample.c: 32 - 8 - 2).
PRECISION_BITS = 22
BICUBIC_SUPPORT = 2.0


def _bicubic_filter(x: np.ndarray) -> np.ndarray:
  """Pillow's bicubic kernel (Keys, a = -0.5), same operation order as Resample.c."""
  a = -0.5
  x = np.abs(x)
  inner = ((a + 2.0) * x - (a + 3.0)) * x * x + 1
  outer = (((x - 5) * x + 8) * x - 4) * a
  return np.where(x < 1.0, inner, np.where(x < 2.0, outer, 0.0))


def _fixed_point_coefficients(input_size: int, output_size: int
                              ) -> tuple[np.ndarray, np.ndarray]:
  """Pillow's `precompute_coeffs` + `normalize_coeffs_8bpc` for the whole axis.

  Returns:
    indices: [output_size, K] int input positions (clamped; their weights are 0 when unused).
    weights: [output_size, K] int64 fixed-point weights summing to ~2**PRECISION_BITS per row.
  """
  scale = input_size / output_size
  filter_scale = max(scale, 1.0)
  support = BICUBIC_SUPPORT * filter_scale
  kernel_size = int(np.ceil(support)) * 2 + 1
  centre = (np.arange(output_size) + 0.5) * scale
  # C casts truncate toward zero.
  first = np.maximum(np.trunc(centre - support + 0.5).astype(np.int64), 0)
  count = np.minimum(np.trunc(centre + support + 0.5).astype(np.int64), input_size) - first
  offsets = np.arange(kernel_size)
  used = offsets[None, :] < count[:, None]
  weights = _bicubic_filter((offsets[None, :] + first[:, None] - centre[:, None] + 0.5)
                            * (1.0 / filter_scale))
  weights = np.where(used, weights, 0.0)
  # Summed left to right as the C loop does (np.sum's pairwise order can differ in the last bit).
  total = np.zeros((output_size, 1))
  for column in range(kernel_size):
    total = total + weights[:, column:column + 1]
  weights = np.where(total != 0.0, weights / np.where(total != 0.0, total, 1.0), weights)
  scaled = weights * (1 << PRECISION_BITS)
  fixed = np.where(scaled < 0, np.trunc(-0.5 + scaled), np.trunc(0.5 + scaled)).astype(np.int64)
  indices = np.minimum(first[:, None] + offsets[None, :], input_size - 1)
  return indices, fixed


def _resample_axis(image: np.ndarray, output_size: int, axis: int) -> np.ndarray:
  """One Pillow pass along `axis` of a uint8 [H, W, C] image: fixed-point sums, clipped."""
  indices, weights = _fixed_point_coefficients(image.shape[axis], output_size)
  gathered = np.take(image.astype(np.int64), indices, axis=axis)  # axis -> (out, K)
  weights = weights.reshape(weights.shape + (1,) * (image.ndim - axis - 1))
  sums = np.sum(gathered * weights, axis=axis + 1) + (1 << (PRECISION_BITS - 1))
  return np.clip(sums >> PRECISION_BITS, 0, 255).astype(np.uint8)


def pil_bicubic_resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
  """`PIL.Image.fromarray(image).resize((width, height), Image.BICUBIC)` of a uint8 [H, W, C]."""
  image = np.asarray(image)
  if image.dtype != np.uint8:
    raise TypeError(f"expected uint8 pixels, got {image.dtype}")
  input_height, input_width = image.shape[:2]
  # Pillow >= 13 runs the vertical pass first when the height shrinks by more than twice as
  # many pixels as the width; the uint8 rounding between the passes makes the order visible.
  shrink_height, shrink_width = input_height - height, input_width - width
  axes = (0, 1) if 0 < shrink_height and shrink_height > 2 * shrink_width else (1, 0)
  for axis in axes:
    size = (height, width)[axis]
    if image.shape[axis] != size:  # Pillow skips a pass whose size does not change.
      image = _resample_axis(image, size, axis)
  return image


def to_uint8(images) -> np.ndarray:
  """uint8 images unchanged; floats in [0, 1] rounded to the nearest grey level."""
  images = np.asarray(images)
  if images.dtype == np.uint8:
    return images
  return np.round(np.clip(images, 0.0, 1.0) * 255).astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class CLIPPreprocessing:
  """The fields of a CLIP `preprocessor_config.json` this module implements."""

  shortest_edge: int = 224
  crop_height: int = 224
  crop_width: int = 224
  image_mean: tuple[float, float, float] = OPENAI_CLIP_MEAN
  image_std: tuple[float, float, float] = OPENAI_CLIP_STD

  @classmethod
  def from_dict(cls, config: Mapping[str, Any], source: str | os.PathLike | None = None
                ) -> "CLIPPreprocessing":
    """From a transformers `preprocessor_config.json` (sizes as dicts or, in old files, ints).

    Options that change the pipeline (another resample filter, no crop, no normalisation) are
    refused rather than silently ignored.
    """
    for field, expected in (("resample", PIL_BICUBIC), ("do_resize", True),
                            ("do_center_crop", True), ("do_rescale", True),
                            ("do_normalize", True)):
      if config.get(field, expected) != expected:
        raise InputError(f"only {field}={expected!r} is implemented, got {config[field]!r}",
                         source, field)
    if config.get("rescale_factor", 1 / 255) != 1 / 255:
      raise InputError("only rescale_factor=1/255 is implemented", source, "rescale_factor")
    size = config.get("size", {"shortest_edge": cls.shortest_edge})
    size = size if isinstance(size, Mapping) else {"shortest_edge": size}
    if "shortest_edge" not in size:
      raise InputError(f"expected a shortest_edge size, got {size!r}", source, "size")
    crop = config.get("crop_size", {"height": cls.crop_height, "width": cls.crop_width})
    crop = crop if isinstance(crop, Mapping) else {"height": crop, "width": crop}
    return cls(shortest_edge=int(size["shortest_edge"]), crop_height=int(crop["height"]),
               crop_width=int(crop["width"]),
               image_mean=tuple(float(v) for v in config.get("image_mean", OPENAI_CLIP_MEAN)),
               image_std=tuple(float(v) for v in config.get("image_std", OPENAI_CLIP_STD)))

  def resized_shape(self, height: int, width: int) -> tuple[int, int]:
    """transformers' `get_resize_output_image_size(..., default_to_square=False)`."""
    short, long = (width, height) if width <= height else (height, width)
    new_short, new_long = self.shortest_edge, int(self.shortest_edge * long / short)
    return (new_long, new_short) if width <= height else (new_short, new_long)

  def __call__(self, images) -> np.ndarray:
    """[N, H, W, 3] uint8 or float in [0, 1] -> [N, crop_height, crop_width, 3] float32."""
    images = to_uint8(images)
    if images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(f"expected [N, H, W, 3] RGB images, got shape {images.shape}")
    height, width = self.resized_shape(*images.shape[1:3])
    if height < self.crop_height or width < self.crop_width:
      raise ValueError(f"the resized {height}x{width} image is smaller than the "
                       f"{self.crop_height}x{self.crop_width} crop")
    top, left = (height - self.crop_height) // 2, (width - self.crop_width) // 2
    crops = np.stack([pil_bicubic_resize(image, height, width)
                      [top:top + self.crop_height, left:left + self.crop_width]
                      for image in images])
    # As transformers: rescale in float64, cast to float32, normalise in float32.
    scaled = (crops.astype(np.float64) * (1 / 255)).astype(np.float32)
    return ((scaled - np.asarray(self.image_mean, np.float32))
            / np.asarray(self.image_std, np.float32))
