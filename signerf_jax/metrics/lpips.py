"""LPIPS (Zhang et al. 2018), VGG variant, in Flax: a differentiable perceptual distance / loss.

Reproduces the `lpips` package's `LPIPS(net='vgg', version='0.1')`:
  1. inputs in [0, 1] are mapped to [-1, 1] (the package's `normalize=True`), then shifted and
     scaled per channel (`ScalingLayer`: shift (-0.030, -0.088, -0.188), scale (0.458, 0.448,
     0.450));
  2. VGG16's convolutional `features` (3x3 convolutions with padding 1, ReLU, 2x2 max pooling)
     are tapped after relu1_2, relu2_2, relu3_3, relu4_3 and relu5_3 (64, 128, 256, 512, 512
     channels, at 1, 1/2, 1/4, 1/8 and 1/16 of the resolution);
  3. each tap is normalised to unit length over channels at every pixel (with the package's
     +1e-10 in the denominator), the two images' taps are subtracted and squared;
  4. a learned non-negative 1x1 convolution without bias (`NetLinLayer`) maps each layer's
     squared difference to one channel, which is averaged over the image;
  5. the five layer scores are summed: one distance per image pair.

Weights are user-provided (the package neither ships nor downloads them), in one safetensors
file with torchvision's VGG16 names for the backbone and the lpips package's names for the
linear layers:
  features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.weight  [out, in, 3, 3]   (torchvision vgg16)
  features.{...}.bias                                   [out]
  lin{0..4}.model.1.weight                              [1, C, 1, 1]      (lpips weights/v0.1/vgg.pth)
`experiments/convert_lpips_weights.py` writes that file from torchvision's VGG16 state dict and
the lpips package's `vgg.pth`.

Everything is a pure function of (params, images), jittable and differentiable, for use as a
fine-tuning loss on NeRF renders. The per-pixel norm uses a square root with a finite derivative
at zero (an all-zero feature vector after the ReLU would otherwise give NaN gradients, as it does
in the package); values are unchanged.
"""

from __future__ import annotations

import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from signerf_jax import math as safe_math
from signerf_jax import safetensors_io

# torchvision's VGG16 ("D") up to relu5_3: convolutions per block and their output channels.
BLOCK_CONVOLUTIONS = (2, 2, 3, 3, 3)
TAP_CHANNELS = (64, 128, 256, 512, 512)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
NORMALIZE_EPSILON = 1e-10
# Each pooling halves the size; relu5_3 comes after four of them.
MIN_IMAGE_SIZE = 2**(len(BLOCK_CONVOLUTIONS) - 1)


def convolution_indices() -> list[tuple[int, int, int]]:
  """(index in torchvision's `features`, input channels, output channels) of each convolution."""
  layers, index, channels = [], 0, 3
  for block, count in enumerate(BLOCK_CONVOLUTIONS):
    if block:
      index += 1  # The max pooling layer before the block.
    for _ in range(count):
      layers.append((index, channels, TAP_CHANNELS[block]))
      channels = TAP_CHANNELS[block]
      index += 2  # Convolution, ReLU.
  return layers


class VGG16Features(nn.Module):
  """torchvision's `vgg16().features` up to relu5_3, channels last."""

  @nn.compact
  def __call__(self, images: jax.Array) -> tuple[jax.Array, ...]:
    """[B, H, W, 3] -> the five taps [B, H / 2^k, W / 2^k, TAP_CHANNELS[k]]."""
    taps, hidden, layers = [], images, iter(convolution_indices())
    for block, count in enumerate(BLOCK_CONVOLUTIONS):
      if block:
        hidden = nn.max_pool(hidden, (2, 2), strides=(2, 2))
      for _ in range(count):
        index, _, channels = next(layers)
        hidden = nn.relu(nn.Conv(channels, (3, 3), padding=((1, 1), (1, 1)),
                                 name=f"features_{index}")(hidden))
      taps.append(hidden)
    return tuple(taps)


def normalize_channels(features: jax.Array) -> jax.Array:
  """lpips' `normalize_tensor`: features / (|features| over channels + 1e-10)."""
  norm = safe_math.safe_sqrt(jnp.sum(features**2, axis=-1, keepdims=True))
  return features / (norm + NORMALIZE_EPSILON)


class LPIPS(nn.Module):
  """LPIPS(net='vgg', version='0.1') distance between image pairs."""

  @nn.compact
  def __call__(self, images: jax.Array, references: jax.Array) -> jax.Array:
    """images, references: [B, H, W, 3] in [0, 1] with H, W >= 16. Returns [B] distances."""
    if images.shape != references.shape or images.ndim != 4 or images.shape[-1] != 3:
      raise ValueError(f"expected two [B, H, W, 3] batches of one shape, got {images.shape} "
                       f"and {references.shape}")
    if min(images.shape[1:3]) < MIN_IMAGE_SIZE:
      raise ValueError(f"images must be at least {MIN_IMAGE_SIZE} pixels on each side, got "
                       f"{images.shape[1:3]}")
    both = jnp.concatenate([images, references]) * 2.0 - 1.0
    both = (both - jnp.asarray(SHIFT)) / jnp.asarray(SCALE)
    distance = jnp.zeros(images.shape[0], images.dtype)
    for layer, tap in enumerate(VGG16Features(name="vgg")(both)):
      first, second = jnp.split(normalize_channels(tap), 2)
      score = nn.Dense(1, use_bias=False, name=f"lin_{layer}")((first - second)**2)
      distance = distance + jnp.mean(score, axis=(1, 2, 3))
    return distance


@jax.jit
def lpips_distance(params, images, references) -> jax.Array:
  """[B] LPIPS distances between [B, H, W, 3] `images` and `references` in [0, 1].

  Differentiable in both images; use `jnp.mean(lpips_distance(...))` as a loss.
  """
  return LPIPS().apply({"params": params}, jnp.asarray(images, jnp.float32),
                       jnp.asarray(references, jnp.float32))


def expected_shapes() -> dict[str, tuple[int, ...]]:
  """Tensor name -> PyTorch shape of every weight (see the module docstring)."""
  shapes = {}
  for index, in_channels, out_channels in convolution_indices():
    shapes[f"features.{index}.weight"] = (out_channels, in_channels, 3, 3)
    shapes[f"features.{index}.bias"] = (out_channels,)
  for layer, channels in enumerate(TAP_CHANNELS):
    shapes[f"lin{layer}.model.1.weight"] = (1, channels, 1, 1)
  return shapes


def params_from_tensors(tensors, source: str | os.PathLike) -> dict:
  """Flax params from the named tensors, after checking every name and shape."""
  safetensors_io.check_tensors(expected_shapes(), tensors, source)
  flat = {}
  for index, _, _ in convolution_indices():
    # torch [out, in, kh, kw] -> Flax [kh, kw, in, out].
    flat[("vgg", f"features_{index}", "kernel")] = np.transpose(
        tensors[f"features.{index}.weight"], (2, 3, 1, 0))
    flat[("vgg", f"features_{index}", "bias")] = tensors[f"features.{index}.bias"]
  for layer, channels in enumerate(TAP_CHANNELS):
    flat[(f"lin_{layer}", "kernel")] = tensors[f"lin{layer}.model.1.weight"].reshape(channels, 1)
  return jax.tree.map(jnp.asarray, traverse_util.unflatten_dict(flat))


def load_lpips_params(path: str | os.PathLike) -> dict:
  """The LPIPS weights of one safetensors file (names in the module docstring)."""
  return params_from_tensors(safetensors_io.read_safetensors(path), path)
