"""Attention: the chunked path equals plain softmax attention and stays within its memory bound."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion.attention import AttentionOptions, dot_product_attention

CHUNKED = AttentionOptions(query_chunk_size=64, max_plain_scores=0)
attention = jax.jit(dot_product_attention, static_argnums=(3, 4))


def reference_attention(query, key, value):
  """softmax(q k^T / sqrt(d)) v in float64 numpy, per head."""
  query, key, value = (np.asarray(x, np.float64) for x in (query, key, value))
  scores = np.einsum("bqhd,bkhd->bhqk", query, key) / np.sqrt(query.shape[-1])
  weights = np.exp(scores - scores.max(-1, keepdims=True))
  weights /= weights.sum(-1, keepdims=True)
  return np.einsum("bhqk,bkhd->bqhd", weights, value)


def random_qkv(query_tokens, key_tokens, heads=3, head_dim=8, seed=0, scale=3.0):
  """Large-magnitude inputs so the softmax is peaked and a missing max-shift would overflow."""
  keys = jax.random.split(jax.random.key(seed), 3)
  shapes = [(2, query_tokens, heads, head_dim)] + [(2, key_tokens, heads, head_dim)] * 2
  return [scale * jax.random.normal(k, s) for k, s in zip(keys, shapes)]


@pytest.mark.parametrize("query_tokens, key_tokens, options", [
    (256, 256, AttentionOptions()), (256, 256, CHUNKED), (200, 77, CHUNKED), (65, 300, CHUNKED)])
def test_matches_softmax_attention(query_tokens, key_tokens, options):
  """Token counts that are not multiples of the chunk exercise the query padding."""
  query, key, value = random_qkv(query_tokens, key_tokens)
  out = attention(query, key, value, options)
  assert out.shape == query.shape and out.dtype == jnp.float32
  np.testing.assert_allclose(out, reference_attention(query, key, value), atol=2e-5, rtol=0)


def test_bfloat16_compute_is_close():
  query, key, value = random_qkv(128, 128, scale=1.0)
  expected = reference_attention(query, key, value)
  for options in (AttentionOptions(), CHUNKED):
    out = attention(query, key, value, options, jnp.bfloat16)
    assert out.dtype == jnp.float32
    error = np.abs(np.asarray(out) - expected).max()
    assert 1e-5 < error < 5e-2  # bf16 rounding, not garbage (and bf16 really was used).


def test_chunked_path_never_holds_the_full_score_matrix():
  """4,096 tokens, one head: the full score matrix is 64 MB; a 256-query chunk is 4 MB."""
  tokens, chunk = 4096, 256
  query, key, value = (jax.ShapeDtypeStruct((1, tokens, 1, 8), jnp.float32),) * 3
  full_scores_bytes = tokens * tokens * 4

  def temporary_bytes(options):
    compiled = attention.lower(query, key, value, options).compile()
    return compiled.memory_analysis().temp_size_in_bytes

  plain = temporary_bytes(AttentionOptions(max_plain_scores=tokens * tokens))
  assert plain > full_scores_bytes / 2
  chunked = temporary_bytes(AttentionOptions(query_chunk_size=chunk, max_plain_scores=0))
  assert chunked < 4 * chunk * tokens * 4
