"""Memory-bounded multi-head attention and the transformer layers of the UNet.

`dot_product_attention` never builds the full [batch, heads, queries, keys] score tensor for
large inputs: above `AttentionOptions.max_plain_scores` score elements it walks over the
batch x heads one at a time, within a head over equal chunks of at most `query_chunk_size`
queries (`lax.map`), and within a chunk over blocks of at most `key_chunk_size` keys with an
online softmax (Rabe & Staats 2021, "Self-attention does not need O(n^2) memory"; FlashAttention's
loop): each block's scores are exponentiated against the running row maximum, and the running
sum and weighted values are rescaled when a later block raises it. The live score block is
[query chunk, key block] -- 2 MB by default, whatever the sheet size -- so it stays in the CPU's
cache between the two matmuls and the softmax. The result equals plain softmax attention up to
float rounding. Only tiny problems use the plain batched einsum.

On a CPU, float32 attention instead runs a fused kernel of the same loop (cpu_attention.py: the
scores stay in registers and cache: faster than XLA's ops, docs/performance.md) where it
builds and the head size suits it; its gradient is the XLA path's. Both are CPU choices: on GPUs
and TPUs attention is `jax.nn.dot_product_attention` with the implementation JAX picks (cuDNN's
fused attention where JAX takes it), over chunks of queries (`attention_path`).
"""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import lax

from signerf_jax import validation
from signerf_jax.diffusion import cpu_attention
from signerf_jax.diffusion.layers import (Conv2d, Dtype, GroupNorm, LayerNorm, Linear,
                                         backend_or_default)
from signerf_jax.validation import NonNegativeInt, PositiveInt


@dataclasses.dataclass(frozen=True)
class AttentionOptions(validation.CheckedFields):
  """How attention is evaluated (results agree to float rounding; speed and memory differ;
  gin: `AttentionOptions.<field>`).

  Attributes:
    query_chunk_size: most queries per chunk in the chunked path (the queries are split into
      equal chunks, so 1,536 queries make two of 768); on GPUs and TPUs, most queries per call
      of `jax.nn.dot_product_attention`, whose XLA implementation holds a chunk's
      [batch, heads, chunk, keys] scores at once.
    key_chunk_size: most keys per block of a chunk's online softmax (keys split likewise); the
      live score block of one head is [query chunk, key block] float32. At least the key count
      (e.g. 2**31) evaluates each chunk against all keys at once.
    max_plain_scores: largest batch * heads * queries * keys evaluated as one plain einsum
      (2**18 elements = 1 MB of float32 scores); larger problems take the chunked path, which
      on CPU is also the faster one from a few hundred tokens up.
    cpu_kernel: float32 attention on a CPU backend runs the fused kernel (cpu_attention.py)
      where it builds and takes the head size; the three fields above then apply only to its
      gradient. False: always XLA's ops. GPUs and TPUs ignore it.
  """
  query_chunk_size: PositiveInt = 1024
  key_chunk_size: PositiveInt = 512
  max_plain_scores: NonNegativeInt = 2**18
  cpu_kernel: bool = True


def _equal_chunks(tokens: int, most: int) -> tuple[int, int]:
  """(chunks, chunk size): the fewest chunks of at most `most` tokens, as equal as padding by
  fewer than `chunks` tokens allows."""
  chunks = -(-tokens // most)
  return chunks, -(-tokens // chunks)


def _block_scores(queries: jax.Array, keys: jax.Array, valid: jax.Array | None) -> jax.Array:
  """Scores [Q, K] float32 of queries [Q, D] against keys [K, D]; -inf where `valid` [K] is
  False (padding keys), so they get zero weight."""
  scores = lax.dot_general(queries, keys, (((1,), (1,)), ((), ())),
                           preferred_element_type=jnp.float32)
  return scores if valid is None else jnp.where(valid, scores, -jnp.inf)


def _attend_chunk(queries: jax.Array, keys: jax.Array, values: jax.Array,
                  valid: jax.Array | None, compute_dtype: Dtype) -> jax.Array:
  """Softmax attention of queries [Q, D] over keys and values [blocks, block, D] (`valid`
  [blocks, block] marks the real keys; None: all are) -> [Q, D] float32."""
  if keys.shape[0] == 1:  # One block holds every key: no padding, no running rescale.
    scores = _block_scores(queries, keys[0], None)
    unnormalised = jnp.exp(scores - jnp.max(scores, axis=-1, keepdims=True))
    out = jnp.dot(unnormalised.astype(compute_dtype), values[0],
                  preferred_element_type=jnp.float32)
    return out / jnp.sum(unnormalised, axis=-1, keepdims=True)

  def attend_one_block(state, inputs):
    # state: the running row maximum [Q], the sum of exp(score - maximum) [Q] and the values
    # weighted by it [Q, D], over the blocks so far.
    running_max, running_sum, weighted = state
    block_keys, block_values, block_valid = inputs
    scores = _block_scores(queries, block_keys, block_valid)
    new_max = jnp.maximum(running_max, jnp.max(scores, axis=-1))
    unnormalised = jnp.exp(scores - new_max[:, None])
    rescale = jnp.exp(running_max - new_max)  # 0 at the first block: the max starts at -inf.
    weighted = weighted * rescale[:, None] + jnp.dot(
        unnormalised.astype(compute_dtype), block_values, preferred_element_type=jnp.float32)
    return (new_max, running_sum * rescale + jnp.sum(unnormalised, axis=-1), weighted), None

  count = queries.shape[0]
  start = (jnp.full((count,), -jnp.inf), jnp.zeros((count,)), jnp.zeros((count, keys.shape[-1])))
  (_, total, weighted), _ = lax.scan(attend_one_block, start, (keys, values, valid))
  return weighted / total[:, None]


def attention_path(head_dim: int, compute_dtype: Dtype, options: AttentionOptions,
                   backend: str | None = None) -> str:
  """How `dot_product_attention` computes heads of `head_dim` channels on `backend` (None: JAX's
  default): "cpu_kernel", the fused kernel (a CPU, float32, `options.cpu_kernel`, a head size
  it takes, and it builds here: `cpu_attention.load`); "xla_chunked", XLA's ops as described
  above (any other case on a CPU); or "jax_nn", `jax.nn.dot_product_attention` (GPUs, TPUs)."""
  if backend_or_default(backend) != "cpu":
    return "jax_nn"
  if (options.cpu_kernel and jnp.dtype(compute_dtype) == jnp.float32
      and cpu_attention.supports(head_dim) and cpu_attention.load()):
    return "cpu_kernel"
  return "xla_chunked"


def dot_product_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                          options: AttentionOptions = AttentionOptions(),
                          compute_dtype: Dtype = jnp.float32,
                          backend: str | None = None) -> jax.Array:
  """softmax(q k^T / sqrt(d)) v per head, by `attention_path`'s choice for `backend`.

  Args:
    query: [B, Tq, H, D].
    key, value: [B, Tk, H, D].
    options: the fused CPU kernel or XLA's ops; plain-versus-chunked switch and chunk sizes.
    compute_dtype: input dtype of the two matmuls (they accumulate in float32; the softmax is
      always float32).
    backend: "cpu", "gpu" or "tpu"; None: the one JAX computes on.

  Returns:
    [B, Tq, H, D] float32.
  """
  head_dim = query.shape[-1]
  query = (query * head_dim**-0.5).astype(compute_dtype)
  key, value = key.astype(compute_dtype), value.astype(compute_dtype)
  path = attention_path(head_dim, compute_dtype, options, backend)
  if path == "cpu_kernel":
    return _kernel_attention(query, key, value, options)
  if path == "jax_nn":
    return _library_attention(query, key, value, options)
  return _scaled_attention(query, key, value, options, compute_dtype)


def _library_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                       options: AttentionOptions) -> jax.Array:
  """`jax.nn.dot_product_attention` (JAX picks the implementation) on inputs already scaled and
  cast, over equal chunks of at most `options.query_chunk_size` queries: JAX's XLA
  implementation holds all of a call's scores, which for a whole sheet's tokens would be tens
  of gigabytes. -> [B, Tq, H, D] float32."""
  batch, query_tokens, heads, head_dim = query.shape
  attend = lambda queries: jax.nn.dot_product_attention(queries, key, value, scale=1.0)
  chunks, chunk = _equal_chunks(query_tokens, options.query_chunk_size)
  if chunks == 1:
    return attend(query).astype(jnp.float32)
  query = jnp.pad(query, ((0, 0), (0, chunks * chunk - query_tokens), (0, 0), (0, 0)))
  out = lax.map(attend, query.reshape(batch, chunks, chunk, heads, head_dim).swapaxes(0, 1))
  out = out.swapaxes(0, 1).reshape(batch, chunks * chunk, heads, head_dim)
  return out[:, :query_tokens].astype(jnp.float32)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _kernel_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                      options: AttentionOptions) -> jax.Array:
  """The fused kernel on scaled float32 inputs; differentiated through XLA's ops."""
  del options  # Only the gradient's XLA path reads it.
  return cpu_attention.attention(query, key, value)


def _kernel_attention_forward(query, key, value, options):
  return _kernel_attention(query, key, value, options), (query, key, value)


def _kernel_attention_backward(options, inputs, out_gradient):
  _, pullback = jax.vjp(lambda *qkv: _scaled_attention(*qkv, options, jnp.float32), *inputs)
  return pullback(out_gradient)


_kernel_attention.defvjp(_kernel_attention_forward, _kernel_attention_backward)


def _scaled_attention(query: jax.Array, key: jax.Array, value: jax.Array,
                      options: AttentionOptions, compute_dtype: Dtype) -> jax.Array:
  """dot_product_attention through XLA's ops, on inputs already scaled and cast."""
  batch, query_tokens, heads, head_dim = query.shape
  key_tokens = key.shape[1]
  if batch * heads * query_tokens * key_tokens <= options.max_plain_scores:
    scores = jnp.einsum("bqhd,bkhd->bhqk", query, key, preferred_element_type=jnp.float32)
    weights = jax.nn.softmax(scores, axis=-1).astype(compute_dtype)
    return jnp.einsum("bhqk,bkhd->bqhd", weights, value, preferred_element_type=jnp.float32)

  chunks, chunk = _equal_chunks(query_tokens, options.query_chunk_size)
  blocks, block = _equal_chunks(key_tokens, options.key_chunk_size)
  # Padded queries attend harmlessly and are sliced off below; padded keys are masked out.
  pad = lambda x, size: jnp.pad(x, ((0, 0), (0, size - x.shape[1]), (0, 0), (0, 0)))
  query = pad(query, chunks * chunk)
  key, value = pad(key, blocks * block), pad(value, blocks * block)
  valid = None
  if blocks * block != key_tokens:
    valid = (jnp.arange(blocks * block) < key_tokens).reshape(blocks, block)
  # One (batch, head) pair at a time: [B*H, chunks, chunk, D] queries, [B*H, blocks, block, D]
  # keys and values.
  per_head = lambda x, count, size: x.transpose(0, 2, 1, 3).reshape(batch * heads, count, size,
                                                                     head_dim)
  query = per_head(query, chunks, chunk)
  key, value = per_head(key, blocks, block), per_head(value, blocks, block)

  def attend_one_head(inputs):
    head_queries, head_keys, head_values = inputs
    return lax.map(lambda queries: _attend_chunk(queries, head_keys, head_values, valid,
                                                 compute_dtype), head_queries)

  out = lax.map(attend_one_head, (query, key, value))  # [B*H, chunks, chunk, D]
  out = out.reshape(batch, heads, chunks * chunk, head_dim)[:, :, :query_tokens]
  return out.transpose(0, 2, 1, 3)


def multi_head_attention(x: jax.Array, context: jax.Array, heads: int, head_dim: int,
                         out_features: int, qkv_bias: bool, options: AttentionOptions,
                         compute_dtype: Dtype) -> jax.Array:
  """Projections to_q/to_k/to_v, attention, then to_out.0: x [B, T, C], context [B, S, C_ctx].

  Creates its Linear layers in the calling module's scope, so the caller must be inside a
  compact method; the parameter names are diffusers' Attention's.
  """
  inner = heads * head_dim

  def project(name, inputs):
    projected = Linear(inner, qkv_bias, compute_dtype, name=name)(inputs)
    return projected.reshape(*inputs.shape[:-1], heads, head_dim)

  out = dot_product_attention(project("to_q", x), project("to_k", context),
                              project("to_v", context), options, compute_dtype)
  out = out.reshape(*x.shape[:-1], inner)
  return Linear(out_features, name="to_out_0", compute_dtype=compute_dtype)(out)


class Attention(nn.Module):
  """diffusers' Attention: x [B, T, C] attends to `context` (or itself) -> [B, T, out_features]."""
  heads: int
  head_dim: int
  out_features: int
  qkv_bias: bool = False
  options: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, context: jax.Array | None = None) -> jax.Array:
    return multi_head_attention(x, x if context is None else context, self.heads, self.head_dim,
                                self.out_features, self.qkv_bias, self.options, self.compute_dtype)


class GEGLU(nn.Module):
  """proj -> value * gelu(gate), the gate being the second half of the projection."""
  inner: int
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    value, gate = jnp.split(Linear(2 * self.inner, name="proj",
                                   compute_dtype=self.compute_dtype)(x), 2, axis=-1)
    return value * jax.nn.gelu(gate, approximate=False)


class GEGLUFeedForward(nn.Module):
  """diffusers' FeedForward with GEGLU: net.0 (GEGLU, 4 x dim wide: diffusers' `mult`, 4 in every
  Stable Diffusion UNet) -> net.2 (Linear)."""
  dim: int
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    hidden = GEGLU(4 * self.dim, self.compute_dtype, name="net_0")(x)
    return Linear(self.dim, name="net_2", compute_dtype=self.compute_dtype)(hidden)


class BasicTransformerBlock(nn.Module):
  """Self-attention, cross-attention and GEGLU feed-forward, each pre-LayerNorm and residual, on
  x [B, T, heads * head_dim]. Built only by `Transformer2D`, which passes every field."""
  heads: int
  head_dim: int
  options: AttentionOptions
  compute_dtype: Dtype

  @nn.compact
  def __call__(self, x: jax.Array, context: jax.Array) -> jax.Array:
    width = self.heads * self.head_dim
    attention = lambda name: Attention(self.heads, self.head_dim, width, options=self.options,
                                       compute_dtype=self.compute_dtype, name=name)
    x = x + attention("attn1")(LayerNorm(name="norm1")(x))
    x = x + attention("attn2")(LayerNorm(name="norm2")(x), context)
    return x + GEGLUFeedForward(width, compute_dtype=self.compute_dtype, name="ff")(
        LayerNorm(name="norm3")(x))


class Transformer2D(nn.Module):
  """diffusers' Transformer2DModel on continuous NHWC input.

  x [B, H, W, C], context [B, S, C_ctx] -> [B, H, W, C]. `use_linear_projection` (SD 2.x,
  SDXL) makes proj_in/proj_out dense layers; otherwise they are 1x1 convolutions (SD 1.x): the
  same matmul in NHWC, but stored with a different weight shape.
  """
  heads: int
  head_dim: int
  num_layers: int
  groups: int
  use_linear_projection: bool
  options: AttentionOptions = AttentionOptions()
  compute_dtype: Dtype = jnp.float32

  @nn.compact
  def __call__(self, x: jax.Array, context: jax.Array) -> jax.Array:
    batch, height, width, channels = x.shape
    inner = self.heads * self.head_dim

    def projection(features, name):
      if self.use_linear_projection:
        return Linear(features, name=name, compute_dtype=self.compute_dtype)
      return Conv2d(features, kernel_size=1, padding=0, name=name, compute_dtype=self.compute_dtype)

    h = GroupNorm(self.groups, 1e-6, name="norm")(x)
    h = projection(inner, "proj_in")(h).reshape(batch, height * width, inner)
    for index in range(self.num_layers):
      h = BasicTransformerBlock(self.heads, self.head_dim, self.options, self.compute_dtype,
                                name=f"transformer_blocks_{index}")(h, context)
    h = projection(channels, "proj_out")(h.reshape(batch, height, width, inner))
    return h + x
