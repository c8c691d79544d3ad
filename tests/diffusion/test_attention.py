"""Attention: XLA's chunked path and the fused CPU kernel equal plain softmax attention; the
chunked path stays within its memory bound."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import attention as attention_lib
from signerf_jax.diffusion.attention import AttentionOptions, dot_product_attention

KERNEL = AttentionOptions()  # The fused CPU kernel (cpu_attention.py); these tests run on a CPU.
PLAIN = AttentionOptions(cpu_kernel=False)
CHUNKED = AttentionOptions(query_chunk_size=64, max_plain_scores=0, cpu_kernel=False)
# Chunks of queries and blocks of keys (the online softmax).
BLOCKED = AttentionOptions(query_chunk_size=64, key_chunk_size=64, max_plain_scores=0,
                           cpu_kernel=False)
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
    (256, 256, PLAIN), (256, 256, CHUNKED), (200, 77, CHUNKED), (65, 300, CHUNKED),
    (256, 256, BLOCKED), (200, 300, BLOCKED), (65, 301, BLOCKED), (64, 65, BLOCKED),
    (256, 256, KERNEL), (200, 77, KERNEL), (65, 301, KERNEL), (1, 97, KERNEL)])
def test_matches_softmax_attention(query_tokens, key_tokens, options):
  """Token counts that are not multiples of the chunk exercise the query padding; with key
  blocks, 301 keys (5 blocks of 61) and 65 (2 of 33) the masked padding keys; for the kernel
  (blocks of 64 queries and 96 keys) partial blocks of both."""
  query, key, value = random_qkv(query_tokens, key_tokens)
  out = attention(query, key, value, options)
  assert out.shape == query.shape and out.dtype == jnp.float32
  np.testing.assert_allclose(out, reference_attention(query, key, value), atol=2e-5, rtol=0)


@pytest.mark.parametrize("tokens, most, expected", [
    (4096, 1024, (4, 1024)), (1536, 1024, (2, 768)), (77, 512, (1, 77)), (300, 64, (5, 60)),
    (301, 64, (5, 61)), (1, 64, (1, 1))])
def test_tokens_split_into_the_fewest_equal_chunks(tokens, most, expected):
  assert attention_lib._equal_chunks(tokens, most) == expected  # pylint: disable=protected-access


@pytest.mark.parametrize("options", [BLOCKED, KERNEL])
@pytest.mark.parametrize("peak_block", [0, 2, 4])
def test_online_softmax_survives_a_dominant_key_in_any_block(peak_block, options):
  """Scores of ~300: one key per query far above the rest, in the first, a middle or the last
  of 5 key blocks (XLA's; the kernel's 96-key blocks: the first, second or third of 4). A later
  maximum rescales the earlier blocks' sums to 0 (the kernel: to ~1e-38 of them); an earlier one
  makes the later blocks' exponentials underflow; neither may give inf or NaN."""
  query, key, value = random_qkv(64, 320, heads=1, scale=1.0)
  key = key.at[:, 64 * peak_block + 7].set(300.0 * query[:, 0] / jnp.linalg.norm(query[:, 0]))
  query = query.at[:, :].set(query[:, :1])  # Every query is the first: the peak is the same key.
  out = attention(query, key, value, options)
  assert np.isfinite(np.asarray(out)).all()
  np.testing.assert_allclose(out, reference_attention(query, key, value), atol=2e-5, rtol=0)
  np.testing.assert_allclose(out[:, 0], value[:, 64 * peak_block + 7], atol=2e-5)


@pytest.mark.parametrize("options", [BLOCKED, KERNEL])
def test_gradients_are_finite_and_match_plain_attention(options):
  """The kernel has no derivative of its own: its gradient is XLA's path's."""
  query, key, value = random_qkv(64, 200, scale=2.0)
  loss = lambda options: lambda q, k, v: jnp.sum(jnp.sin(attention(q, k, v, options)))
  plain = jax.grad(loss(dataclasses.replace(PLAIN, max_plain_scores=2**30)),
                   argnums=(0, 1, 2))(query, key, value)
  tested = jax.grad(loss(options), argnums=(0, 1, 2))(query, key, value)
  for expected, got in zip(plain, tested):
    assert np.isfinite(np.asarray(got)).all()
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=0)


@pytest.mark.parametrize("options", [BLOCKED, KERNEL])
def test_a_second_call_with_new_values_does_not_recompile(options):
  query, key, value = random_qkv(65, 301)
  attention(query, key, value, options)
  compiled = attention._cache_size()  # pylint: disable=protected-access
  attention(query + 1, key, value * 2, options)
  assert attention._cache_size() == compiled  # pylint: disable=protected-access


@pytest.mark.slow
def test_bfloat16_compute_is_close():
  query, key, value = random_qkv(128, 128, scale=1.0)
  expected = reference_attention(query, key, value)
  for options in (KERNEL, PLAIN, CHUNKED, BLOCKED):  # bfloat16 never takes the kernel.
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

  plain = temporary_bytes(dataclasses.replace(PLAIN, max_plain_scores=tokens * tokens))
  assert plain > full_scores_bytes / 2
  every_key = dataclasses.replace(CHUNKED, query_chunk_size=chunk, key_chunk_size=tokens)
  chunked = temporary_bytes(every_key)
  assert chunked < 4 * chunk * tokens * 4
  # Blocks of 512 keys: the live score block is 512 KB, a chunk against every key 4 MB.
  blocked = temporary_bytes(dataclasses.replace(every_key, key_chunk_size=512))
  assert blocked < 4 * chunk * 512 * 4 < chunked
