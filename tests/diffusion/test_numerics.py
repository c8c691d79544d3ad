"""Every convolution and attention path, in float32 and bfloat16, against float64 on hard inputs.

The error of a result y against the float64 reference r is the largest over output channels of
max |y - r| / max |r| (over the channel's positions): each channel relative to its own scale, so
channels whose sums cancel to small outputs count as much as large ones. The bounds, per compute
dtype (a bfloat16 path rounds its inputs too, so its bound covers that):

- convolutions: 5e-5 in float32, 2e-2 in bfloat16. Measured (float32 / bfloat16) on the inputs
  below: direct ways (im2col, XLA's, a 1x1 matmul) <= 2.5e-6 / 5.7e-3; Winograd F(2x2) 8.8e-7 /
  5.7e-3; F(4x4) 1.4e-5 / 8.4e-2, over the bfloat16 bound, so the CPU choice never takes it in
  bfloat16; nearest x2 upsampling then a convolution (`upsample_conv`) 5.9e-7 / 4.3e-3. With
  seeds 0-2 and 64 to 1280 channels: F(2x2) <= 7.5e-3 and F(4x4) >= 6.8e-2 in bfloat16, F(4x4)
  <= 2.1e-5 in float32.
- attention: 5e-5 in float32, 3e-2 in bfloat16 (rounding queries and keys to bfloat16 moves the
  scores, which the softmax exponentiates). Measured: the fused CPU kernel 1.1e-5 (float32 only:
  the kernel takes nothing else), XLA's chunked ops and `jax.nn.dot_product_attention` 8.7e-6 /
  1.2e-2.

Every path runs here, on the CPU, whatever backend would choose it (GPUs and TPUs take XLA's
convolution and `jax.nn.dot_product_attention`; their own kernels are not tested here).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import cpu_attention, layers
from signerf_jax.diffusion.attention import (AttentionOptions, attention_path,
                                             dot_product_attention)

DTYPES = ("float32", "bfloat16")
CONVOLUTION_BOUNDS = {"float32": 5e-5, "bfloat16": 2e-2}
ATTENTION_BOUNDS = {"float32": 5e-5, "bfloat16": 3e-2}

# Each path as a function of (x [B, H, W, C], kernel [3, 3, C, O], compute dtype) and the float64
# convolution it computes; the 1x1 matmul takes the kernel's centre tap.
CONVOLUTIONS = {
    "matmul": lambda x, kernel, dtype: layers.matmul(x, kernel[1, 1], dtype),
    "im2col": lambda x, kernel, dtype: layers.im2col_conv(x, kernel, 1, 1, dtype),
    "xla": lambda x, kernel, dtype: layers.xla_conv(x, kernel, 1, 1, dtype),
    "winograd_2x2": layers.winograd_2x2_conv3x3,
    "winograd_4x4": layers.winograd_4x4_conv3x3,
    "upsample": layers.upsample_conv,
}
# The paths whose error exceeds their dtype's bound: the CPU choice must never take them.
OVER_THE_BOUND = {("winograd_4x4", "bfloat16")}


def channel_relative_error(result, reference: np.ndarray) -> float:
  """Largest over the last (channel) axis of max |result - reference| / max |reference|."""
  error = np.abs(np.asarray(result, np.float64) - reference)
  positions = tuple(range(reference.ndim - 1))
  return float((error.max(positions) / np.abs(reference).max(positions)).max())


def reference_convolution(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
  """Same-size convolution (stride 1, padding (k - 1) / 2) of x [B, H, W, C] by a square kernel
  [k, k, C, O] in float64 numpy -> [B, H, W, O]."""
  x, kernel = np.asarray(x, np.float64), np.asarray(kernel, np.float64)
  size = kernel.shape[0]
  height, width = x.shape[1:3]
  pad = size // 2
  padded = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
  patches = np.concatenate([padded[:, dy:dy + height, dx:dx + width]
                            for dy in range(size) for dx in range(size)], axis=-1)
  return patches @ kernel.reshape(-1, kernel.shape[-1])


@functools.cache
def convolution_inputs() -> tuple[np.ndarray, np.ndarray]:
  """x [1, 16, 16, 320] of 1e3-scale activations around an offset of 1e3, and an SD-scaled kernel
  [3, 3, 320, 64] whose first 32 output channels have their 3x3 window's mean removed, so those
  channels cancel the offset: sums of 1e3-sized terms to far smaller outputs."""
  rng = np.random.default_rng(0)
  x = 1e3 * (rng.standard_normal((1, 16, 16, 320)) + 1)
  kernel = rng.standard_normal((3, 3, 320, 64)) / np.sqrt(9 * 320)
  kernel[..., :32] -= kernel[..., :32].mean(axis=(0, 1), keepdims=True)
  return x.astype(np.float32), kernel.astype(np.float32)


@functools.cache
def convolution_error(algorithm: str, dtype: str) -> float:
  x, kernel = convolution_inputs()
  if algorithm == "matmul":
    reference = reference_convolution(x, kernel[1:2, 1:2])
  elif algorithm == "upsample":
    reference = reference_convolution(np.asarray(layers.upsample_nearest(x)), kernel)
  else:
    reference = reference_convolution(x, kernel)
  result = jax.jit(CONVOLUTIONS[algorithm], static_argnums=2)(x, kernel, jnp.dtype(dtype))
  return channel_relative_error(result, reference)


@pytest.mark.parametrize("algorithm, dtype", [
    (algorithm, dtype) for algorithm in CONVOLUTIONS for dtype in DTYPES
    if (algorithm, dtype) not in OVER_THE_BOUND])
def test_convolution_paths_stay_within_their_bound(algorithm, dtype):
  assert convolution_error(algorithm, dtype) <= CONVOLUTION_BOUNDS[dtype]


def cpu_choices(dtype: str) -> set[str]:
  """Every algorithm the CPU choice takes for 3x3 convolutions of SD's UNet and VAE layers, and
  of sheets up to 1024x1536, in batches of 1 to 8."""
  sizes = [(side, side) for side in (8, 16, 32, 64, 128, 256, 512)] + [
      (96, 64), (128, 192), (512, 768), (1024, 1536)]
  return {layers.cpu_convolution_algorithm((batch, height, width, channels),
                                           (3, 3, channels, channels), 1, 1, jnp.dtype(dtype))
          for batch in (1, 2, 4, 8) for height, width in sizes
          for channels in (64, 128, 256, 320, 512, 640, 1280)}


def test_winograd_is_never_chosen_where_its_error_exceeds_the_bound():
  over = {(algorithm, dtype) for algorithm in ("winograd_2x2", "winograd_4x4")
          for dtype in DTYPES if convolution_error(algorithm, dtype) > CONVOLUTION_BOUNDS[dtype]}
  assert over == OVER_THE_BOUND  # F(4x4) in bfloat16, 3x to 5x over.
  for algorithm, dtype in over:
    assert algorithm not in cpu_choices(dtype)
  # The sizes above reach Winograd's: in float32 both tile sizes are taken.
  assert {"winograd_2x2", "winograd_4x4"} <= cpu_choices("float32")
  assert "winograd_2x2" in cpu_choices("bfloat16")


def reference_attention(query: np.ndarray, key: np.ndarray, value: np.ndarray) -> np.ndarray:
  """softmax(q k^T / sqrt(d)) v per batch entry and head in float64 numpy: [B, Tq, H, D]."""
  query, key, value = (np.asarray(x, np.float64) for x in (query, key, value))
  out = np.empty(query.shape)
  for batch in range(query.shape[0]):
    for head in range(query.shape[2]):
      scores = query[batch, :, head] @ key[batch, :, head].T / np.sqrt(query.shape[-1])
      weights = np.exp(scores - scores.max(axis=-1, keepdims=True))
      out[batch, :, head] = weights @ value[batch, :, head] / weights.sum(-1, keepdims=True)
  return out


@functools.cache
def attention_inputs() -> tuple[np.ndarray, ...]:
  """4,001 queries over 4,096 keys, 2 heads of 40 (SD's), and the float64 result. Queries and
  keys N(0, 4): each row's scores span ~29, a peaked softmax. The keys' first channel is a
  constant 128 (the massive activations transformers grow), shifting each query's scores by up
  to ~160: exp overflows float32 without the running maximum. Values 1e3-scale around 1e3."""
  rng = np.random.default_rng(0)
  query = 2 * rng.standard_normal((1, 4001, 2, 40))
  key = 2 * rng.standard_normal((1, 4096, 2, 40))
  key[..., 0] = 128
  value = 1e3 * (rng.standard_normal((1, 4096, 2, 40)) + 1)
  query, key, value = (x.astype(np.float32) for x in (query, key, value))
  return query, key, value, reference_attention(query, key, value)


# Each path: the options and backend that make `dot_product_attention` take it.
ATTENTION_PATHS = {
    "cpu_kernel": (AttentionOptions(), "cpu"),
    "xla_chunked": (AttentionOptions(cpu_kernel=False), "cpu"),
    "jax_nn": (AttentionOptions(), "gpu"),
}


@pytest.mark.parametrize("path, dtype", [
    ("cpu_kernel", "float32"), ("xla_chunked", "float32"), ("xla_chunked", "bfloat16"),
    ("jax_nn", "float32"), ("jax_nn", "bfloat16")])
def test_attention_paths_stay_within_their_bound(path, dtype):
  if path == "cpu_kernel" and cpu_attention.unmet_requirement() is not None:
    pytest.skip(cpu_attention.unmet_requirement())
  options, backend = ATTENTION_PATHS[path]
  assert attention_path(40, jnp.dtype(dtype), options, backend) == path
  query, key, value, reference = attention_inputs()
  attend = jax.jit(lambda *qkv: dot_product_attention(*qkv, options, jnp.dtype(dtype), backend))
  assert channel_relative_error(attend(query, key, value), reference) <= ATTENTION_BOUNDS[dtype]
