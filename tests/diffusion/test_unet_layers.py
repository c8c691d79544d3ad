"""The UNet's fast convolution paths equal plain convolution; GroupNorm equals its definition."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from signerf_jax.diffusion import layers


def direct_conv(x, kernel):
  return lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)),
                                  dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                  precision=lax.Precision.HIGHEST)


def random_conv_inputs(height, width, channels=8, out=5, seed=0):
  x_key, kernel_key = jax.random.split(jax.random.key(seed))
  return (jax.random.normal(x_key, (2, height, width, channels)),
          jax.random.normal(kernel_key, (3, 3, channels, out)) / np.sqrt(9 * channels))


@pytest.mark.parametrize("height, width", [(6, 10), (2, 2)])
def test_winograd_equals_direct_convolution(height, width):
  x, kernel = random_conv_inputs(height, width)
  out = jax.jit(layers.winograd_conv3x3, static_argnums=2)(x, kernel, jnp.float32)
  np.testing.assert_allclose(out, direct_conv(x, kernel), atol=1e-5, rtol=0)


@pytest.mark.parametrize("kernel_size, stride, padding", [
    (3, 1, ((1, 1), (1, 1))), (3, 2, ((0, 1), (0, 1))), (2, 1, ((1, 1), (1, 1)))])
def test_im2col_equals_direct_convolution(kernel_size, stride, padding):
  x, _ = random_conv_inputs(7, 6)
  kernel = jax.random.normal(jax.random.key(3), (kernel_size, kernel_size, 8, 5))
  out = jax.jit(layers.im2col_conv, static_argnums=(2, 3, 4))(x, kernel, stride, padding,
                                                                jnp.float32)
  expected = lax.conv_general_dilated(
      x, kernel, (stride, stride), padding, dimension_numbers=("NHWC", "HWIO", "NHWC"),
      precision=lax.Precision.HIGHEST)
  np.testing.assert_allclose(out, expected, atol=1e-4, rtol=0)


def test_conv2d_picks_the_algorithm_by_size():
  kernel = jnp.zeros((3, 3, 64, 64))

  def primitives(shape, compute_dtype=jnp.float32):
    jaxpr = jax.make_jaxpr(lambda x: layers.conv2d(x, kernel, 1, 1, compute_dtype))(
        jax.ShapeDtypeStruct(shape, jnp.float32))
    return {str(equation.primitive) for equation in jaxpr.eqns}

  winograd, im2col, odd = (2, 32, 32, 64), (2, 16, 16, 64), (2, 32, 31, 64)
  huge = (1, 1024, 1536, 64)
  assert "conv_general_dilated" not in primitives(winograd)
  assert "concatenate" in primitives(im2col) and "conv_general_dilated" not in primitives(im2col)
  assert "conv_general_dilated" in primitives(odd)  # neither fast path applies
  assert "conv_general_dilated" in primitives(huge)  # Winograd would need 1.6 GB
  assert "conv_general_dilated" not in primitives(odd, jnp.bfloat16)  # im2col: bf16 matmul
  with layers.winograd_convolutions(False):
    assert "conv_general_dilated" in primitives(winograd)
    assert "conv_general_dilated" not in primitives(im2col)  # Only Winograd is turned off.
    with layers.winograd_convolutions(True):
      assert "conv_general_dilated" not in primitives(winograd)
    assert "conv_general_dilated" in primitives(winograd)
  assert "conv_general_dilated" not in primitives(winograd)  # Back on after the block.


@pytest.mark.parametrize("height, width", [(5, 7), (1, 1)])
def test_upsample_conv_equals_upsampling_then_convolution(height, width):
  x, kernel = random_conv_inputs(height, width)
  out = jax.jit(layers.upsample_conv, static_argnums=2)(x, kernel, jnp.float32)
  np.testing.assert_allclose(out, direct_conv(layers.upsample_nearest(x), kernel), atol=1e-5,
                             rtol=0)


def test_upsample_nearest_to_a_given_size_follows_torch():
  x = jnp.arange(3.0)[None, :, None, None] * jnp.ones((1, 3, 2, 1))
  rows = layers.upsample_nearest(x, (5, 4))[0, :, 0, 0]
  np.testing.assert_array_equal(rows, [0, 0, 1, 1, 2])  # floor(i * 3 / 5)


def test_group_norm_matches_its_definition():
  x = 3.0 + jax.random.normal(jax.random.key(1), (2, 4, 5, 12))
  params = {"params": {"scale": jnp.linspace(0.5, 2, 12), "bias": jnp.linspace(-1, 1, 12)}}
  out = layers.GroupNorm(num_groups=3, epsilon=1e-5).apply(params, x)
  grouped = np.asarray(x, np.float64).reshape(2, 20, 3, 4)
  mean = grouped.mean(axis=(1, 3), keepdims=True)
  variance = grouped.var(axis=(1, 3), keepdims=True)
  expected = ((grouped - mean) / np.sqrt(variance + 1e-5)).reshape(x.shape)
  expected = expected * params["params"]["scale"] + params["params"]["bias"]
  np.testing.assert_allclose(out, expected, atol=2e-5, rtol=0)
