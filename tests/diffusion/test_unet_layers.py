"""The UNet's fast convolution paths equal plain convolution; GroupNorm equals its definition."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from signerf_jax.diffusion import layers, winograd


def direct_conv(x, kernel):
  return lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)),
                                  dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                  precision=lax.Precision.HIGHEST)


def random_conv_inputs(height, width, channels=8, out=5, seed=0):
  x_key, kernel_key = jax.random.split(jax.random.key(seed))
  return (jax.random.normal(x_key, (2, height, width, channels)),
          jax.random.normal(kernel_key, (3, 3, channels, out)) / np.sqrt(9 * channels))


@pytest.mark.parametrize("function, height, width, tolerance", [
    (layers.winograd_2x2_conv3x3, 6, 10, 1e-5), (layers.winograd_2x2_conv3x3, 2, 2, 1e-5),
    (layers.winograd_4x4_conv3x3, 8, 12, 5e-5), (layers.winograd_4x4_conv3x3, 4, 4, 5e-5)],
    ids=["2x2-tiles", "2x2-one-tile", "4x4-tiles", "4x4-one-tile"])
def test_winograd_equals_direct_convolution(function, height, width, tolerance):
  x, kernel = random_conv_inputs(height, width)
  out = jax.jit(function, static_argnums=2)(x, kernel, jnp.float32)
  np.testing.assert_allclose(out, direct_conv(x, kernel), atol=tolerance, rtol=0)


def test_winograd_4x4_error_at_a_large_layer():
  """F(4x4)'s larger transform constants cost accuracy: at 320 channels (SD's first level) the
  error stays ~2e-5 of the outputs' scale, under the diffusers parity tolerance of 1e-4."""
  x, kernel = random_conv_inputs(16, 16, channels=320, out=64)
  expected = direct_conv(x, kernel)
  error = np.abs(np.asarray(jax.jit(layers.winograd_4x4_conv3x3, static_argnums=2)(
      x, kernel, jnp.float32)) - np.asarray(expected)).max()
  assert error < 5e-5 * np.abs(np.asarray(expected)).max()


def test_winograd_needs_whole_tiles():
  x, kernel = random_conv_inputs(6, 8)
  with pytest.raises(ValueError, match="divisible by 4; got 6x8"):
    winograd.conv3x3(x, kernel, jnp.float32, output_tile=4)


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


def test_conv2d_picks_the_cpu_algorithm_by_size():
  def algorithm(shape, compute_dtype=jnp.float32):
    return layers.cpu_convolution_algorithm(shape, (3, 3, 64, 64), 1, 1, compute_dtype)

  four_tiles, two_tiles = (2, 64, 64, 64), (2, 32, 32, 64)
  im2col, odd = (2, 16, 16, 64), (2, 32, 31, 64)
  assert algorithm(four_tiles) == "winograd_4x4"  # 512 4x4 tiles
  assert algorithm(two_tiles) == "winograd_2x2"  # 128 4x4 tiles, 512 2x2 ones
  assert algorithm((2, 64, 62, 64)) == "winograd_2x2"  # 62 is not a multiple of 4
  assert algorithm(im2col) == "im2col"
  assert algorithm(odd) == "xla"  # neither fast path applies
  assert algorithm((1, 768, 768, 64)) == "winograd_4x4"  # 340 MB; F(2x2) would take 604
  assert algorithm((1, 1024, 1536, 64)) == "xla"  # Winograd would need 0.9 GB (F(4x4))
  assert algorithm(odd, jnp.bfloat16) == "im2col"  # bf16 matmul
  assert algorithm(four_tiles, jnp.bfloat16) == "winograd_2x2"  # F(4x4) is too inexact in bf16
  with layers.winograd_convolutions(False):
    assert algorithm(four_tiles) == algorithm(two_tiles) == "xla"
    assert algorithm(im2col) == "im2col"  # Only Winograd is turned off.
    with layers.winograd_convolutions(True):
      assert algorithm(two_tiles) == "winograd_2x2"
    assert algorithm(two_tiles) == "xla"
  assert algorithm(two_tiles) == "winograd_2x2"  # Back on after the block.


@pytest.mark.parametrize("shape, algorithm", [
    ((2, 64, 64, 64), "winograd_4x4"), ((2, 32, 32, 64), "winograd_2x2"),
    ((2, 16, 16, 64), "im2col"), ((2, 32, 31, 64), "xla")])
def test_conv2d_computes_by_the_algorithm_it_picks(shape, algorithm):
  """Read from the traced program: XLA's convolution, im2col's concatenated patches, or a
  Winograd rewrite (a custom gradient around a matmul batched over the 36 or 16 positions)."""
  kernel = jnp.zeros((3, 3, 64, 64))
  jaxpr = jax.make_jaxpr(lambda x: layers.conv2d(x, kernel, 1, 1, jnp.float32))(
      jax.ShapeDtypeStruct(shape, jnp.float32))
  primitives = {str(equation.primitive): equation for equation in jaxpr.eqns}
  if algorithm == "xla":
    assert "conv_general_dilated" in primitives
    return
  assert "conv_general_dilated" not in primitives
  if algorithm == "im2col":
    assert "concatenate" in primitives
    return
  matmuls = [equation.invars[0].aval.shape
             for equation in primitives["custom_vjp_call"].params["call_jaxpr"].jaxpr.eqns
             if str(equation.primitive) == "dot_general"]
  assert [shape[0] for shape in matmuls] == [36 if algorithm == "winograd_4x4" else 16]


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
