"""Numerically safe elementwise functions whose values *and gradients* stay finite.

Each function clamps its input to the range where the plain function is finite, and defines its
derivative from the clamped input, so `jax.grad` never meets inf * 0 = nan at the guard.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

TINY = float(jnp.finfo(jnp.float32).tiny)
EPSILON = float(jnp.finfo(jnp.float32).eps)
# exp(88.7) is the largest finite float32; stay a little below it.
MAX_EXP_INPUT = 88.0


def with_derivative(derivative):
  """Decorator: the elementwise function it wraps gets the derivative `derivative(x)` (a
  `jax.custom_jvp`, tangent = derivative(x) * x_dot), written from a guarded input so that it
  stays finite where the plain function's is not."""

  def decorate(function):
    guarded = jax.custom_jvp(function)
    guarded.defjvp(lambda primals, tangents: (guarded(primals[0]),
                                               derivative(primals[0]) * tangents[0]))
    return guarded

  return decorate


@with_derivative(lambda x: jnp.exp(jnp.minimum(x, MAX_EXP_INPUT)))
def safe_exp(x):
  """exp(min(x, 88)): finite for any finite input, with a finite derivative."""
  return jnp.exp(jnp.minimum(x, MAX_EXP_INPUT))


@with_derivative(lambda x: 1.0 / jnp.maximum(x, TINY))
def safe_log(x):
  """log(max(x, tiny)): finite for x <= 0, derivative 1 / max(x, tiny)."""
  return jnp.log(jnp.maximum(x, TINY))


@with_derivative(lambda x: 0.5 / jnp.sqrt(jnp.maximum(x, EPSILON)))
def safe_sqrt(x):
  """sqrt(max(x, 0)) whose derivative at 0 is large but finite, not inf."""
  return jnp.sqrt(jnp.maximum(x, 0.0))


def safe_div(numerator, denominator, eps: float = 1e-10):
  """numerator / denominator, with |denominator| clamped to >= eps (sign kept; 0 -> +eps).

  eps = 1e-10 keeps the derivative -numerator / denominator**2 finite in float32 (1e20);
  a float32-tiny clamp would overflow it to inf and turn gradients into nan.
  """
  sign = jnp.where(denominator < 0, -1.0, 1.0)
  return numerator / (sign * jnp.maximum(jnp.abs(denominator), eps))


def safe_normalize(vector, axis: int = -1, eps: float = 1e-12):
  """vector / |vector| along `axis`; zero vectors stay zero (with zero gradient)."""
  squared_norm = jnp.sum(vector**2, axis=axis, keepdims=True)
  return vector * jax.lax.rsqrt(jnp.maximum(squared_norm, eps**2))

