import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax import math as safe_math

HARD_INPUTS = [-1e30, -100.0, -1.0, 0.0, 1e-30, 1e-10, 1.0, 88.0, 100.0, 1e10, 1e30]


@pytest.mark.parametrize("function", [safe_math.safe_exp, safe_math.safe_log, safe_math.safe_sqrt])
@pytest.mark.parametrize("x", HARD_INPUTS)
def test_values_and_gradients_are_finite(function, x):
  value, gradient = jax.value_and_grad(function)(jnp.float32(x))
  assert np.isfinite(value) and np.isfinite(gradient)


def test_safe_functions_match_plain_ones_in_range():
  x = jnp.linspace(0.01, 20.0, 101)
  np.testing.assert_allclose(safe_math.safe_exp(x), jnp.exp(x), rtol=1e-6)
  np.testing.assert_allclose(safe_math.safe_log(x), jnp.log(x), rtol=1e-6)
  np.testing.assert_allclose(safe_math.safe_sqrt(x), jnp.sqrt(x), rtol=1e-6)
  np.testing.assert_allclose(jax.vmap(jax.grad(safe_math.safe_sqrt))(x), 0.5 / jnp.sqrt(x),
                             rtol=1e-5)


@pytest.mark.parametrize("denominator", [0.0, -0.0, 1e-40, -1e-40, 2.0, -2.0])
def test_safe_div_is_finite_and_exact_away_from_zero(denominator):
  value, gradient = jax.value_and_grad(safe_math.safe_div, argnums=(0, 1))(1.0, denominator)
  assert np.isfinite(value) and all(np.isfinite(g) for g in gradient)
  if abs(denominator) > 1:
    assert value == 1.0 / denominator


def test_safe_normalize_keeps_zero_vectors_zero():
  vectors = jnp.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
  np.testing.assert_allclose(safe_math.safe_normalize(vectors), [[0.6, 0.8, 0.0], [0, 0, 0]])
  gradient = jax.grad(lambda v: safe_math.safe_normalize(v).sum())(vectors)
  assert np.all(np.isfinite(gradient))
