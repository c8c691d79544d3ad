// Fused softmax attention for x86-64 CPUs with AVX2 and FMA, float32, as an XLA FFI handler.
//
// out[b, i, h] = sum_j softmax_j(q[b, i, h] . k[b, j, h]) v[b, j, h] for q [..., Tq, H, D] (already
// scaled by 1/sqrt(D)) and k, v [..., Tk, H, D]; every leading axis is a batch axis. Like
// FlashAttention, each block of queries walks over blocks of keys with an online softmax, so the
// scores never leave the cache: XLA's ops write each score block to memory between the two
// matmuls, the softmax's passes and the rescale, and the matmuls' 40-wide operands (SD 1.5's head
// size) run Eigen's kernels at ~60% of the CPU's matmul speed.
//
// The block works transposed -- scores^T [keys x queries] and out^T [D x queries] -- so the
// softmax over keys runs down columns in whole vectors (no horizontal reductions), and both
// matmuls are one register-blocked micro-kernel: 6 rows x 16 columns, 12 accumulators. Work is
// split over (batch, head, span of queries) on XLA's intra-op thread pool.
//
// Built on first use by signerf_jax/diffusion/cpu_attention.py (-O3 -march=native).

#include <immintrin.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int kRows = 6;            // Micro-tile rows: keys of the scores, channels of the output.
constexpr int kQueryBlock = 64;     // Queries per block: four micro-tiles of 16 columns.
constexpr int kKeyBlock = 96;       // Keys per block (a multiple of kRows): 24 KB of scores.
constexpr int kTasksPerThread = 8;  // Tasks per pool thread, where the queries allow.
constexpr int kMaxHeadDim = 160;    // Kept in step with cpu_attention.py's MAX_HEAD_DIM.
constexpr float kLog2E = 1.44269504088896341f;  // Base-2 scores: exp(s) = 2^(s log2(e)).

// 2^x for x <= 0 (base-2 scores minus their running maximum), within 1 ulp: 2^n p(r) with
// n = round(x) and r = x - n in [-1/2, 1/2] (exact), p a degree-6 polynomial fitted to 2^r
// (relative error 2e-9 before float32 rounding). Base 2 -- the packed queries carry the factor
// log2(e) -- spares exp's range reduction by ln 2. Below -126 it returns 2^-126 ~ 1.2e-38 instead
// of a smaller number (or 0): negligible beside the row's largest weight, 2^0 = 1.
inline __m256 exp2_non_positive(__m256 x) {
  x = _mm256_max_ps(x, _mm256_set1_ps(-126.0f));
  const __m256 n = _mm256_round_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  const __m256 r = _mm256_sub_ps(x, n);
  __m256 p = _mm256_set1_ps(1.5346250439e-4f);
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.3399935560e-3f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(9.6184872091e-3f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(5.5503286421e-2f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(2.4022646248e-1f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(6.9314718246e-1f));
  p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.0f));
  const __m256i two_to_n = _mm256_slli_epi32(
      _mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
  return _mm256_mul_ps(p, _mm256_castsi256_ps(two_to_n));
}

// c[R x 16] (=, or += with Accumulate) a[R x K] . b[K x 16]: a[r][k] at a[r * a_row + k * a_col],
// b and c with rows kQueryBlock floats apart.
template <int R, bool Accumulate>
inline void micro_tile(const float* a, int64_t a_row, int64_t a_col, const float* b, int K,
                       float* c) {
  __m256 sum[R][2];
  for (int r = 0; r < R; ++r) {
    sum[r][0] = Accumulate ? _mm256_loadu_ps(c + r * kQueryBlock) : _mm256_setzero_ps();
    sum[r][1] = Accumulate ? _mm256_loadu_ps(c + r * kQueryBlock + 8) : _mm256_setzero_ps();
  }
  for (int k = 0; k < K; ++k) {
    const __m256 b0 = _mm256_loadu_ps(b + k * kQueryBlock);
    const __m256 b1 = _mm256_loadu_ps(b + k * kQueryBlock + 8);
    for (int r = 0; r < R; ++r) {
      const __m256 x = _mm256_broadcast_ss(a + r * a_row + k * a_col);
      sum[r][0] = _mm256_fmadd_ps(x, b0, sum[r][0]);
      sum[r][1] = _mm256_fmadd_ps(x, b1, sum[r][1]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm256_storeu_ps(c + r * kQueryBlock, sum[r][0]);
    _mm256_storeu_ps(c + r * kQueryBlock + 8, sum[r][1]);
  }
}

struct Problem {
  const float* query;
  const float* key;
  const float* value;
  float* out;
  int64_t batch, queries, keys, heads, head_dim;
};

// The end of a key block for 8 queries' columns: their running sums and maxima (`previous` before
// the block, `maximum` after it) updated, and their out^T columns rescaled to the new maxima.
// Where none of the 8 maxima moved the rescale is exactly 2^0 = 1, so the pass over out^T is
// skipped without changing a bit.
inline void update_running(__m256 previous, __m256 maximum, __m256 sum, int head_dim,
                           float* running_max, float* running_sum, float* out) {
  // 0 (up to the 2^-126 floor, times the zero sums) at the first block: the maxima start at -inf.
  const __m256 rescale = exp2_non_positive(_mm256_sub_ps(previous, maximum));
  _mm256_storeu_ps(running_sum, _mm256_fmadd_ps(_mm256_loadu_ps(running_sum), rescale, sum));
  _mm256_storeu_ps(running_max, maximum);
  if (_mm256_movemask_ps(_mm256_cmp_ps(maximum, previous, _CMP_NEQ_UQ)) == 0) return;
  for (int d = 0; d < head_dim; ++d)
    _mm256_storeu_ps(out + d * kQueryBlock,
                     _mm256_mul_ps(rescale, _mm256_loadu_ps(out + d * kQueryBlock)));
}

// Softmax over one key block of scores^T [keys x kQueryBlock] (rows >= `keys` are padding): the
// base-2 scores become weights 2^(score - new maximum), and the running maxima, sums and out^T
// rescale. Two 8-query columns (a and b) at a time: two independent chains of maxima and sums to
// overlap, each in its own variable so that the compiler keeps it in a register.
void softmax_block(float* scores, int keys, int padded_keys, int head_dim, float* running_max,
                   float* running_sum, float* out) {
  for (int c = 0; c < kQueryBlock; c += 16) {
    float* column = scores + c;
    const __m256 previous_a = _mm256_loadu_ps(running_max + c);
    const __m256 previous_b = _mm256_loadu_ps(running_max + c + 8);
    __m256 maximum_a = previous_a, maximum_b = previous_b;
    for (int j = 0; j < keys; ++j) {
      maximum_a = _mm256_max_ps(maximum_a, _mm256_loadu_ps(column + j * kQueryBlock));
      maximum_b = _mm256_max_ps(maximum_b, _mm256_loadu_ps(column + j * kQueryBlock + 8));
    }
    __m256 sum_a = _mm256_setzero_ps(), sum_b = _mm256_setzero_ps();
    for (int j = 0; j < keys; ++j) {
      float* row = column + j * kQueryBlock;
      const __m256 weight_a = exp2_non_positive(_mm256_sub_ps(_mm256_loadu_ps(row), maximum_a));
      const __m256 weight_b =
          exp2_non_positive(_mm256_sub_ps(_mm256_loadu_ps(row + 8), maximum_b));
      _mm256_storeu_ps(row, weight_a);
      _mm256_storeu_ps(row + 8, weight_b);
      sum_a = _mm256_add_ps(sum_a, weight_a);
      sum_b = _mm256_add_ps(sum_b, weight_b);
    }
    for (int j = keys; j < padded_keys; ++j) {
      _mm256_storeu_ps(column + j * kQueryBlock, _mm256_setzero_ps());
      _mm256_storeu_ps(column + j * kQueryBlock + 8, _mm256_setzero_ps());
    }
    update_running(previous_a, maximum_a, sum_a, head_dim, running_max + c, running_sum + c,
                   out + c);
    update_running(previous_b, maximum_b, sum_b, head_dim, running_max + c + 8,
                   running_sum + c + 8, out + c + 8);
  }
}

// Queries [begin, end) of one (batch, head) pair.
void attend_span(const Problem& problem, int64_t batch, int64_t head, int64_t begin,
                 int64_t end) {
  const int head_dim = static_cast<int>(problem.head_dim);
  const int64_t token_stride = problem.heads * problem.head_dim;
  const int64_t padded_keys = (problem.keys + kKeyBlock - 1) / kKeyBlock * kKeyBlock;
  // This head's keys and values, contiguous and zero-padded to whole blocks.
  std::vector<float> keys(padded_keys * head_dim, 0.0f), values(padded_keys * head_dim, 0.0f);
  for (int64_t j = 0; j < problem.keys; ++j) {
    const int64_t at = (batch * problem.keys + j) * token_stride + head * head_dim;
    std::memcpy(&keys[j * head_dim], problem.key + at, head_dim * sizeof(float));
    std::memcpy(&values[j * head_dim], problem.value + at, head_dim * sizeof(float));
  }
  std::vector<float> queries_t(head_dim * kQueryBlock), scores_t(kKeyBlock * kQueryBlock),
      out_t(head_dim * kQueryBlock), running_max(kQueryBlock), running_sum(kQueryBlock);
  for (int64_t first = begin; first < end; first += kQueryBlock) {
    const int count = static_cast<int>(std::min<int64_t>(kQueryBlock, end - first));
    std::fill(queries_t.begin(), queries_t.end(), 0.0f);
    for (int i = 0; i < count; ++i) {
      const float* query =
          problem.query + (batch * problem.queries + first + i) * token_stride + head * head_dim;
      for (int d = 0; d < head_dim; ++d) queries_t[d * kQueryBlock + i] = query[d] * kLog2E;
    }
    std::fill(out_t.begin(), out_t.end(), 0.0f);
    std::fill(running_max.begin(), running_max.end(), -INFINITY);
    std::fill(running_sum.begin(), running_sum.end(), 0.0f);
    for (int64_t key0 = 0; key0 < problem.keys; key0 += kKeyBlock) {
      const int block_keys = static_cast<int>(std::min<int64_t>(kKeyBlock, problem.keys - key0));
      const int tiled_keys = (block_keys + kRows - 1) / kRows * kRows;
      // scores^T [keys x queries] = keys [keys x D] . queries^T [D x queries]
      for (int j = 0; j < tiled_keys; j += kRows)
        for (int c = 0; c < kQueryBlock; c += 16)
          micro_tile<kRows, false>(&keys[(key0 + j) * head_dim], head_dim, 1,
                                   &queries_t[c], head_dim, &scores_t[j * kQueryBlock + c]);
      softmax_block(scores_t.data(), block_keys, tiled_keys, head_dim, running_max.data(),
                    running_sum.data(), out_t.data());
      // out^T [D x queries] += values^T [D x keys] . weights^T [keys x queries]; head sizes
      // are multiples of 8, so a remainder of 2 or 4 rows.
      const float* block_values = &values[key0 * head_dim];
      for (int c = 0; c < kQueryBlock; c += 16) {
        int d = 0;
        for (; d + kRows <= head_dim; d += kRows)
          micro_tile<kRows, true>(block_values + d, 1, head_dim, &scores_t[c], tiled_keys,
                                  &out_t[d * kQueryBlock + c]);
        if (head_dim - d == 4)
          micro_tile<4, true>(block_values + d, 1, head_dim, &scores_t[c], tiled_keys,
                              &out_t[d * kQueryBlock + c]);
        else if (head_dim - d == 2)
          micro_tile<2, true>(block_values + d, 1, head_dim, &scores_t[c], tiled_keys,
                              &out_t[d * kQueryBlock + c]);
      }
    }
    for (int i = 0; i < count; ++i) {
      float* out = problem.out + (batch * problem.queries + first + i) * token_stride +
                   head * head_dim;
      const float normaliser = 1.0f / running_sum[i];
      for (int d = 0; d < head_dim; ++d) out[d] = out_t[d * kQueryBlock + i] * normaliser;
    }
  }
}

// What the threads sharing one call's work hold: the problem, the next task to take and the
// count of tasks done. Owned jointly (shared_ptr), because a helper the pool starts late, after
// the caller has finished every task and returned, must still find it.
struct SharedWork {
  Problem problem;
  int64_t spans, span_length, tasks;
  std::atomic<int64_t> next_task{0}, tasks_done{0};
  std::mutex mutex;
  std::condition_variable all_done;
};

void take_tasks(SharedWork& work) {
  for (int64_t task; (task = work.next_task.fetch_add(1)) < work.tasks;) {
    const int64_t span = task % work.spans, pair = task / work.spans;
    attend_span(work.problem, pair / work.problem.heads, pair % work.problem.heads,
                span * work.span_length,
                std::min(work.problem.queries, (span + 1) * work.span_length));
    if (work.tasks_done.fetch_add(1) + 1 == work.tasks) {
      std::lock_guard<std::mutex> lock(work.mutex);
      work.all_done.notify_all();
    }
  }
}

ffi::Error Attention(ffi::ThreadPool pool, ffi::AnyBuffer query, ffi::AnyBuffer key,
                     ffi::AnyBuffer value, ffi::Result<ffi::AnyBuffer> out) {
  const auto query_shape = query.dimensions(), key_shape = key.dimensions();
  const size_t rank = query_shape.size();
  if (query.element_type() != ffi::F32 || key.element_type() != ffi::F32 ||
      value.element_type() != ffi::F32 || rank < 3 || key_shape.size() != rank)
    return ffi::Error::InvalidArgument("query, key, value: float32 [..., tokens, heads, dim]");
  int64_t batch = 1;
  for (size_t axis = 0; axis + 3 < rank; ++axis) batch *= query_shape[axis];
  const Problem problem{query.typed_data<float>(), key.typed_data<float>(),
                        value.typed_data<float>(), out->typed_data<float>(), batch,
                        query_shape[rank - 3], key_shape[rank - 3], query_shape[rank - 2],
                        query_shape[rank - 1]};
  if (problem.head_dim % 8 != 0 || problem.head_dim > kMaxHeadDim)
    return ffi::Error::InvalidArgument("head size must be a multiple of 8 up to 160");
  auto work = std::make_shared<SharedWork>();
  work->problem = problem;
  // Tasks are spans of one (batch, head) pair's queries. Each packs its head's keys and values,
  // so the fewer and longer the spans the less is copied (512-query spans cost ~5% at 4,096
  // tokens); kTasksPerThread tasks per thread still share the work out evenly.
  const int64_t pairs = problem.batch * problem.heads;
  const int64_t blocks = std::max<int64_t>((problem.queries + kQueryBlock - 1) / kQueryBlock, 1);
  const int64_t threads = std::max<int64_t>(pool.num_threads(), 1);
  const int64_t wanted_spans =
      std::clamp<int64_t>(kTasksPerThread * threads / std::max<int64_t>(pairs, 1), 1, blocks);
  work->span_length = (blocks + wanted_spans - 1) / wanted_spans * kQueryBlock;
  work->spans = std::max<int64_t>((problem.queries + work->span_length - 1) / work->span_length, 1);
  work->tasks = pairs * work->spans;
  // The caller takes tasks too and waits only for tasks some thread has taken, never for a
  // helper to start: XLA may run several of these calls at once on its pool, each occupying a
  // pool thread, and waiting for a helper queued behind them would deadlock.
  const int64_t helpers = std::min<int64_t>(pool.num_threads(), work->tasks) - 1;
  for (int64_t helper = 0; helper < helpers; ++helper) pool.Schedule([work] { take_tasks(*work); });
  take_tasks(*work);
  std::unique_lock<std::mutex> lock(work->mutex);
  work->all_done.wait(lock, [&] { return work->tasks_done.load() == work->tasks; });
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(SignerfCpuAttention, Attention,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>());
