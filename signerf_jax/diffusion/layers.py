"""The NHWC layers the UNet, ControlNet and VAE are built from, and how they compute.

Every array here is channels-last: images and feature maps are [batch, height, width, channels]
(XLA's CPU convolutions are faster in NHWC than in NCHW, and no transposes are needed around
the token-wise attention layers). Parameters are stored as Flax expects them: convolution
kernels [kh, kw, in, out] (HWIO), dense kernels [in, out], norm `scale`/`bias` [channels];
`signerf_jax.diffusion.weights` converts diffusers' OIHW / [out, in] tensors into this layout.

The layers are dense (`Linear`), convolution (`Conv2d`, and `UpsampleConv`: nearest upsampling
then a convolution), `GroupNorm` and `LayerNorm`. On a CPU a convolution runs by the algorithm
measured fastest there for its size (`cpu_convolution_algorithm`: an im2col matmul, Winograd's
F(4x4, 3x3) or F(2x2, 3x3) -- `signerf_jax.diffusion.winograd` -- or XLA's own); on GPUs and
TPUs always by XLA's own, which cuDNN or the TPU compiler implement (`convolution_algorithm`).
The rewrites are differentiated as XLA's convolution.

Precision: `compute_dtype` is the dtype of the inputs of matmuls and convolutions (float32, or
bfloat16 for the fast option); they always accumulate and return float32, and normalisation
statistics, softmax and residual sums stay float32 whatever the compute dtype.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from typing import Any, Iterator

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from signerf_jax.diffusion import winograd

Dtype = Any
Padding = int | tuple[tuple[int, int], tuple[int, int]]


def matmul(x: jax.Array, kernel: jax.Array, compute_dtype: Dtype) -> jax.Array:
  """x [..., in] @ kernel [in, out] -> [..., out] float32, inputs cast to `compute_dtype`."""
  return lax.dot_general(x.astype(compute_dtype), kernel.astype(compute_dtype),
                         (((x.ndim - 1,), (0,)), ((), ())), preferred_element_type=jnp.float32)


class Linear(nn.Module):
  """A dense layer: [..., in] -> [..., features] (torch.nn.Linear)."""
  features: int
  use_bias: bool = True
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    kernel = self.param("kernel", nn.initializers.lecun_normal(), (x.shape[-1], self.features),
                        jnp.float32)
    y = matmul(x, kernel, self.compute_dtype)
    if self.use_bias:
      y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
    return y


# How convolutions are computed on CPUs, each way where it measured faster there than XLA's own
# convolution (docs/performance.md; nothing here was measured on GPUs or TPUs, which take XLA's):
# 3x3 same-size ones on small maps as one im2col matmul, on large maps by Winograd's algorithm
# once there are enough output tiles to pay for the input and output transforms (the kernel's
# is computed once a sampler run: XLA hoists it out of the denoising loop), and as long as the
# transformed input stays small -- full-resolution VAE maps of a 1024x1536 sheet would need
# gigabytes. With at least CPU_WINOGRAD_MIN_TILES 4x4 tiles by F(4x4, 3x3) (transformed input
# 2.25x the input), the faster of the two on large maps, else with that many 2x2 tiles by
# F(2x2, 3x3) (4x the input), which stays ahead where 4x4 tiles are too few. XLA's bfloat16
# convolution is no faster than float32 while bfloat16 matmuls are, so with bfloat16 compute
# every other convolution is an im2col matmul too when its patch matrix fits in
# CPU_IM2COL_MAX_BYTES.
CPU_IM2COL_MAX_POSITIONS = 512
CPU_IM2COL_MAX_BYTES = 2**29
CPU_WINOGRAD_MIN_TILES = 512
CPU_WINOGRAD_MIN_CHANNELS = 64
CPU_WINOGRAD_MAX_TRANSFORMED_BYTES = 2**29
# The Winograd output tiles allowed per compute dtype: those whose error stays within the
# dtype's bound (tests/diffusion/test_numerics.py states the bounds and checks them: 5e-5 of
# the outputs' largest magnitude in float32, 2e-2 in bfloat16). In bfloat16, F(4x4)'s
# transforms (constants up to 8, and 1/24) magnify the rounding of the bfloat16 Winograd-domain
# tiles to 7e-2 - 9e-2, against <= 7.5e-3 for F(2x2) and <= 5.7e-3 for a direct convolution.
CPU_WINOGRAD_OUTPUT_TILES = {"float32": (4, 2), "bfloat16": (2,)}


def backend_or_default(backend: str | None) -> str:
  """`backend` as given ("cpu", "gpu", "tpu"), or where None the one JAX computes on
  (`jax.default_backend()`, read when the caller is traced: a program is built for the backend
  it will run on). Tests pass a backend to check each one's choices without its device."""
  return jax.default_backend() if backend is None else backend


# Whether `conv2d` may choose Winograd, for the program being traced (`winograd_convolutions`).
_tracing = threading.local()


@contextlib.contextmanager
def winograd_convolutions(enabled: bool) -> Iterator[None]:
  """Allows (the default) or forbids Winograd convolutions in what is traced inside (they are
  only ever a CPU's choice: `cpu_convolution_algorithm`).

  Winograd's transforms are many small ops for XLA to compile: they make each call faster but
  add more compilation than a program run a few times (the preview's) earns back. A jitted
  function that traces under this must have `enabled` among its static arguments, so that each
  choice is its own compiled program.
  """
  previous = getattr(_tracing, "winograd", True)
  _tracing.winograd = enabled
  try:
    yield
  finally:
    _tracing.winograd = previous


def _explicit_padding(padding: Padding) -> tuple[tuple[int, int], tuple[int, int]]:
  return ((padding, padding), (padding, padding)) if isinstance(padding, int) else padding


def im2col_conv(x: jax.Array, kernel: jax.Array, stride: int, padding: Padding,
                compute_dtype: Dtype) -> jax.Array:
  """A convolution as one [positions, kh*kw*C] x [kh*kw*C, O] matmul over gathered patches.

  x [B, H, W, C], kernel [kh, kw, C, O] -> [B, H', W', O] float32. The patch matrix is
  kh*kw/stride^2 times the input, so this is for small maps (or bfloat16, see above).
  """
  (top, bottom), (left, right) = _explicit_padding(padding)
  kernel_height, kernel_width, channels, _ = kernel.shape
  padded = jnp.pad(x.astype(compute_dtype), ((0, 0), (top, bottom), (left, right), (0, 0)))
  out_height = (padded.shape[1] - kernel_height) // stride + 1
  out_width = (padded.shape[2] - kernel_width) // stride + 1
  patches = jnp.concatenate(
      [padded[:, dy:dy + stride * (out_height - 1) + 1:stride,
              dx:dx + stride * (out_width - 1) + 1:stride]
       for dy in range(kernel_height) for dx in range(kernel_width)], axis=-1)
  return matmul(patches, kernel.reshape(kernel_height * kernel_width * channels, -1),
                compute_dtype)


def xla_conv(x: jax.Array, kernel: jax.Array, stride: int, padding: Padding,
             compute_dtype: Dtype) -> jax.Array:
  """XLA's own NHWC x HWIO convolution -> float32."""
  return lax.conv_general_dilated(
      x.astype(compute_dtype), kernel.astype(compute_dtype), window_strides=(stride, stride),
      padding=_explicit_padding(padding), dimension_numbers=("NHWC", "HWIO", "NHWC"),
      preferred_element_type=jnp.float32)


def _differentiated_as(reference):
  """Gives a fast exact rewrite `fast(x, kernel, compute_dtype)` of a convolution the gradient of
  `reference` (the same function by XLA's convolution). The rewrites' many slices and stacks
  transpose into slow scatters that made a backward pass (training the default model) about
  three times slower than this way, while forward passes keep the fast form."""

  def decorate(fast):
    @functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
    def function(x, kernel, compute_dtype):
      return fast(x, kernel, compute_dtype)

    def forward(x, kernel, compute_dtype):
      return fast(x, kernel, compute_dtype), (x, kernel)

    def backward(compute_dtype, residuals, cotangent):
      return jax.vjp(lambda x, kernel: reference(x, kernel, compute_dtype), *residuals)[1](
          cotangent)

    function.defvjp(forward, backward)
    return function

  return decorate


def _same_size_xla_conv(x: jax.Array, kernel: jax.Array, compute_dtype: Dtype) -> jax.Array:
  return xla_conv(x, kernel, 1, 1, compute_dtype)


@_differentiated_as(_same_size_xla_conv)
def winograd_2x2_conv3x3(x: jax.Array, kernel: jax.Array, compute_dtype: Dtype) -> jax.Array:
  """3x3 convolution, stride 1, padding 1, by Winograd's F(2x2, 3x3) (`winograd.conv3x3`).

  x [B, H, W, C] with H and W even, kernel [3, 3, C, O] (HWIO) -> [B, H, W, O] float32.
  """
  return winograd.conv3x3(x, kernel, compute_dtype, output_tile=2)


@_differentiated_as(_same_size_xla_conv)
def winograd_4x4_conv3x3(x: jax.Array, kernel: jax.Array, compute_dtype: Dtype) -> jax.Array:
  """The same by F(4x4, 3x3): H and W multiples of 4; 4x fewer FLOPs than direct convolution
  (2.25x for F(2x2)), ~2e-5 relative error in float32 but ~8e-2 in bfloat16 (so not chosen
  there: `CPU_WINOGRAD_OUTPUT_TILES`)."""
  return winograd.conv3x3(x, kernel, compute_dtype, output_tile=4)


def convolution_algorithm(x_shape: tuple[int, ...], kernel_shape: tuple[int, ...], stride: int,
                          padding: Padding, compute_dtype: Dtype, backend: str | None = None
                          ) -> str:
  """How `conv2d` computes a convolution of these shapes on `backend` (None: JAX's default):
  on a CPU `cpu_convolution_algorithm`'s choice; on GPUs and TPUs "xla", XLA's own convolution,
  which cuDNN or the TPU compiler run (the CPU thresholds say nothing of those devices, and
  Winograd in bfloat16 would lose accuracy there too)."""
  if backend_or_default(backend) != "cpu":
    return "xla"
  return cpu_convolution_algorithm(x_shape, kernel_shape, stride, padding, compute_dtype)


def cpu_convolution_algorithm(x_shape: tuple[int, ...], kernel_shape: tuple[int, ...],
                              stride: int, padding: Padding, compute_dtype: Dtype) -> str:
  """The fastest way measured on CPUs for a convolution of x [B, H, W, C] by a kernel
  [kh, kw, C, O] (see above): "matmul" (1x1), "im2col", "winograd_4x4", "winograd_2x2" or
  "xla"; Winograd only with output tiles allowed for `compute_dtype`."""
  batch, height, width, channels = x_shape
  kernel_height, kernel_width, _, out = kernel_shape
  if (kernel_height, kernel_width) == (1, 1) and stride == 1 and padding == 0:
    return "matmul"
  if (kernel_height, kernel_width) == (3, 3) and stride == 1 and padding == 1:
    if batch * height * width <= CPU_IM2COL_MAX_POSITIONS:
      return "im2col"
    if getattr(_tracing, "winograd", True) and min(channels, out) >= CPU_WINOGRAD_MIN_CHANNELS:
      for output_tile in CPU_WINOGRAD_OUTPUT_TILES.get(jnp.dtype(compute_dtype).name, ()):
        tiles = batch * height * width // output_tile**2
        transformed_bytes = (output_tile + 2)**2 * tiles * channels * 4  # float32 transforms
        if (height % output_tile == 0 and width % output_tile == 0
            and tiles >= CPU_WINOGRAD_MIN_TILES
            and transformed_bytes <= CPU_WINOGRAD_MAX_TRANSFORMED_BYTES):
          return f"winograd_{output_tile}x{output_tile}"
  patch_bytes = (batch * height * width // stride**2 * kernel_height * kernel_width * channels
                 * jnp.dtype(compute_dtype).itemsize)
  if jnp.dtype(compute_dtype) == jnp.bfloat16 and patch_bytes <= CPU_IM2COL_MAX_BYTES:
    return "im2col"
  return "xla"


def conv2d(x: jax.Array, kernel: jax.Array, stride: int, padding: Padding,
           compute_dtype: Dtype, backend: str | None = None) -> jax.Array:
  """NHWC x HWIO convolution -> float32, by `convolution_algorithm`'s choice for its size and
  `backend` (None: JAX's default)."""
  algorithm = convolution_algorithm(x.shape, kernel.shape, stride, padding, compute_dtype,
                                    backend)
  if algorithm == "matmul":
    return matmul(x, kernel[0, 0], compute_dtype)
  if algorithm == "winograd_4x4":
    return winograd_4x4_conv3x3(x, kernel, compute_dtype)
  if algorithm == "winograd_2x2":
    return winograd_2x2_conv3x3(x, kernel, compute_dtype)
  convolution = im2col_conv if algorithm == "im2col" else xla_conv
  return convolution(x, kernel, stride, padding, compute_dtype)


class Conv2d(nn.Module):
  """A 2-D convolution on NHWC maps (torch.nn.Conv2d with a square kernel).

  Attributes:
    padding: symmetric padding in pixels, or ((top, bottom), (left, right)).
  """
  features: int
  kernel_size: int = 3
  stride: int = 1
  padding: Padding = 1
  use_bias: bool = True
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (self.kernel_size, self.kernel_size, x.shape[-1], self.features),
                        jnp.float32)
    y = conv2d(x, kernel, self.stride, self.padding, self.compute_dtype)
    if self.use_bias:
      y = y + self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
    return y


class GroupNorm(nn.Module):
  """torch.nn.GroupNorm over the channels of [B, ..., C] (statistics per sample and group).

  Sums are taken per channel over the positions first (a reduction along the outer axis of the
  channels-last array, which XLA vectorises over channels), then per group: measured faster on
  CPUs than reducing a [B, positions, groups, channels per group] view directly.
  """
  num_groups: int
  epsilon: float

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    batch, channels = x.shape[0], x.shape[-1]
    per_group = channels // self.num_groups
    scale = self.param("scale", nn.initializers.ones, (channels,), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (channels,), jnp.float32)
    flat = x.astype(jnp.float32).reshape(batch, -1, channels)
    count = flat.shape[1] * per_group

    def group_mean(per_channel_sums):  # [B, C] -> the [B, 1, C] mean of each channel's group
      means = per_channel_sums.reshape(batch, self.num_groups, per_group).sum(-1) / count
      return jnp.repeat(means, per_group, axis=1)[:, None, :]

    mean = group_mean(jnp.sum(flat, axis=1))
    variance = group_mean(jnp.sum(jnp.square(flat - mean), axis=1))  # two-pass, as torch
    channel_scale = lax.rsqrt(variance + self.epsilon) * scale
    return (flat * channel_scale + (bias - mean * channel_scale)).reshape(x.shape)


class LayerNorm(nn.Module):
  """torch.nn.LayerNorm over the last axis."""
  epsilon: float = 1e-5

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    features = x.shape[-1]
    scale = self.param("scale", nn.initializers.ones, (features,), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (features,), jnp.float32)
    x = x.astype(jnp.float32)
    mean = jnp.mean(x, axis=-1, keepdims=True)
    centred = x - mean
    variance = jnp.mean(jnp.square(centred), axis=-1, keepdims=True)  # two-pass, as torch
    return centred * lax.rsqrt(variance + self.epsilon) * scale + bias


def upsample_nearest(x: jax.Array, size: tuple[int, int] | None = None) -> jax.Array:
  """Nearest-neighbour upsampling of [B, H, W, C] by 2, or to `size` (as torch's F.interpolate)."""
  batch, height, width, channels = x.shape
  if size is None or tuple(size) == (2 * height, 2 * width):
    x = jnp.broadcast_to(x[:, :, None, :, None, :], (batch, height, 2, width, 2, channels))
    return x.reshape(batch, 2 * height, 2 * width, channels)
  # torch "nearest": source index = floor(destination * in / out).
  rows = np.minimum(np.floor(np.arange(size[0]) * (height / size[0])).astype(np.int32), height - 1)
  cols = np.minimum(np.floor(np.arange(size[1]) * (width / size[1])).astype(np.int32), width - 1)
  return x[:, rows][:, :, cols]


def _phase_taps(taps: list[jax.Array]) -> list[list[jax.Array]]:
  """Nearest x2 then a 3-tap filter, per output phase p (parity): the phase-p output at i reads
  inputs i - 1 + p and i + p with these summed taps ([phase][window tap])."""
  return [[taps[0], taps[1] + taps[2]], [taps[0] + taps[1], taps[2]]]


@_differentiated_as(lambda x, kernel, compute_dtype: xla_conv(upsample_nearest(x), kernel, 1, 1,
                                                           compute_dtype))
def upsample_conv(x: jax.Array, kernel: jax.Array, compute_dtype: Dtype) -> jax.Array:
  """conv3x3(upsample_nearest(x), kernel) with padding 1, computed at the input resolution.

  The four output phases are 2x2 convolutions of x with summed kernel taps, evaluated as one
  2x2 convolution with 4x the output channels: 16 instead of 36 multiply-adds per output
  channel and input pixel (2.25x fewer FLOPs), then interleaved into the 2x larger map.
  (Tap sums are explicit adds: an einsum with a 0/1 tap matrix compiles to slow transposes.)

  Args:
    x: [B, H, W, C].
    kernel: [3, 3, C, O] (HWIO).

  Returns:
    [B, 2H, 2W, O] float32 (no bias).
  """
  batch, height, width, _ = x.shape
  out = kernel.shape[-1]

  def phase_kernel(p, q):  # [2 (window row), 2 (window column), C, O] of output phase (p, q)
    return jnp.stack([jnp.stack(_phase_taps(list(row))[q])
                      for row in _phase_taps(list(kernel))[p]])

  phase_kernels = jnp.stack([phase_kernel(p, q) for p in (0, 1) for q in (0, 1)], axis=-2)
  phases = conv2d(x, phase_kernels.reshape(2, 2, kernel.shape[2], 4 * out), 1, 1,
                  compute_dtype)
  phases = phases.reshape(batch, height + 1, width + 1, 2, 2, out)
  rows_out = [jnp.stack([phases[:, p:p + height, q:q + width, p, q] for q in (0, 1)], axis=3)
              for p in (0, 1)]  # each [B, H, W, 2 (column phase), O]
  return jnp.stack(rows_out, axis=2).reshape(batch, 2 * height, 2 * width, out)


class UpsampleConv(nn.Module):
  """Nearest upsampling then a 3x3 convolution, with the parameters of that convolution.

  Doubling sizes use `upsample_conv` (2.25x fewer FLOPs); other target sizes (diffusers'
  forced upsample size for latents not divisible by the UNet's total stride) upsample first.
  """
  features: int
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, size: tuple[int, int] | None = None) -> jax.Array:
    kernel = self.param("kernel", nn.initializers.lecun_normal(),
                        (3, 3, x.shape[-1], self.features), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
    if size is None or tuple(size) == (2 * x.shape[1], 2 * x.shape[2]):
      return upsample_conv(x, kernel, self.compute_dtype) + bias
    return conv2d(upsample_nearest(x, size), kernel, 1, 1, self.compute_dtype) + bias
