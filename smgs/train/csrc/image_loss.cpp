// The photometric training loss (1 − λ)·L1 + λ·(1 − SSIM) and its gradient, in one pass on CPU.
//
// Same definition as smgs.metrics.ssim (3DGS: 11-tap separable Gaussian window, zero padding,
// C1, C2, mean of the map) and smgs.train.loss (the analytic backward): the window and constants
// come in as arguments, so they are defined once, in Python. Images are [H, W, C] float32,
// contiguous; a row is W·C floats, so the horizontal taps are C floats apart and both passes run
// over contiguous memory. Also here: the β/γ ray-variance regulariser (the other per-pixel term of
// the training loss).
//
// Why compiled: at 128² the PyTorch version costs ~3 ms a step (two banded matrix products per
// blur and ~40 elementwise ops on 50K floats), more than the renderer's forward and backward at
// a few Gaussians; here it is two small separable blurs and one fused elementwise pass.
//
// Each blur streams: a block of rows blurs its image rows horizontally into a ring of `win` rows and
// reads them back vertically while they are in cache, instead of writing whole [H, W·C] maps and
// reading them again (the same sums in the same order: the same bits), in two parallel regions.
// At 400×300×3 one thread took 7.9 ms against 9.1 ms with whole maps, two threads on a loaded
// 2-core host 26 against 50 ms (half the parallel regions, each waiting for the slower thread).

// The ATen and pybind11 headers these bindings use, not <torch/extension.h>: a third of the build time.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/csrc/utils/pybind.h>

#include <ATen/Parallel.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <vector>

namespace {

// Σ v[e] in double, 8 independent partial sums (a single running sum is neither vectorised without
// -ffast-math nor fast: it is one long dependency chain). The order is fixed: no thread dependence.
inline double row_sum(const float* v, int n) {
  double acc[8] = {0, 0, 0, 0, 0, 0, 0, 0};
  int e = 0;
  for (; e + 8 <= n; e += 8)
    for (int l = 0; l < 8; ++l) acc[l] += double(v[e + l]);
  for (; e < n; ++e) acc[0] += double(v[e]);
  return ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]));
}

constexpr int kMaxWin = 31;

// 16 floats as one value (GCC/Clang vector extension: one AVX-512 register with -march=native on
// this machine, split into narrower registers elsewhere). The blurs below keep each output's sum in
// such a register across the taps: GCC does not vectorise the tap loop inside the element loop.
typedef float F16 __attribute__((vector_size(64)));
constexpr int kL = 16;
inline F16 load16(const float* p) {
  F16 v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
inline void store16(float* p, F16 v) { std::memcpy(p, &v, sizeof v); }

// V vectors of output at once: each sum is one dependency chain of adds (4-cycle latency), so
// enough independent chains must be in flight to keep the vector units busy.
template <int V>
inline void taps_block(const float* const* src, const float* w, int m, float* __restrict out, int e) {
  F16 a[V] = {};
  for (int j = 0; j < m; ++j) {
    const float* p = src[j] + e;
    for (int v = 0; v < V; ++v) a[v] += w[j] * load16(p + v * kL);
  }
  for (int v = 0; v < V; ++v) store16(out + e + v * kL, a[v]);
}

// out[e] = Σ_j w[j]·src[j][e] for j < m, summed in j order (the same sums as tap by tap).
inline void taps(const float* const* src, const float* w, int m, float* __restrict out, int n) {
  int e = 0;
  for (; e + 8 * kL <= n; e += 8 * kL) taps_block<8>(src, w, m, out, e);
  for (; e + kL <= n; e += kL) taps_block<1>(src, w, m, out, e);
  for (; e < n; ++e) {
    float acc = 0.f;
    for (int j = 0; j < m; ++j) acc += w[j] * src[j][e];
    out[e] = acc;
  }
}

// Horizontal pass: out[e] = Σ_k g[k]·in[e + (k − r)·C] over one row of n = W·C floats, zero outside.
// `pad` is scratch of n + 2·r·C floats.
inline void blur_row(const float* in, float* __restrict out, float* __restrict pad, int n, int C, const float* g,
                     int win) {
  const int r = win / 2, off = r * C;
  for (int e = 0; e < off; ++e) pad[e] = 0.f;
  for (int e = 0; e < n; ++e) pad[off + e] = in[e];
  for (int e = 0; e < off; ++e) pad[off + n + e] = 0.f;
  const float* src[kMaxWin];
  for (int k = 0; k < win; ++k) src[k] = pad + k * C;
  taps(src, g, win, out, n);
}

// The rows of a map blurred horizontally that a vertical pass reads, kept for `win` image rows at a time
// (a ring: image row `row` in slot row % win, each of `maps` maps n floats), so that a block of output
// rows streams through a few hundred kilobytes instead of writing and re-reading whole [H, n] maps.
struct RowRing {
  int win, maps, n;
  std::unique_ptr<float[]> buf;
  RowRing(int win_, int maps_, int n_) : win(win_), maps(maps_), n(n_), buf(new float[size_t(win_) * maps_ * n_]) {}
  float* row(int m, int image_row) { return buf.get() + (int64_t(image_row % win) * maps + m) * n; }
};

// Vertical pass for output row i of map m of a ring holding the rows i − r .. i + r that exist: zero
// outside the image; the taps summed in window order (the sums of a pass over the whole map).
inline void blur_col(RowRing& ring, int m, float* __restrict out, int i, int H, const float* g, int win) {
  const int r = win / 2;
  const float* src[kMaxWin];
  float w[kMaxWin];
  int k_used = 0;
  for (int k = 0; k < win; ++k) {
    const int row = i + k - r;
    if (row < 0 || row >= H) continue;
    src[k_used] = ring.row(m, row);
    w[k_used++] = g[k];
  }
  taps(src, w, k_used, out, ring.n);
}

// Output rows [i0, i1) of a separable blur, streamed: `fill(row)` writes the horizontally blurred rows
// of image row `row` into the ring (each row once per block, those within r of the block's ends
// twice over the blocks), `emit(i)` reads output row i's vertical sums from it.
template <class Fill, class Emit>
inline void stream_rows(int64_t i0, int64_t i1, int H, int win, Fill fill, Emit emit) {
  const int r = win / 2;
  int next = int(std::max<int64_t>(0, i0 - r));   // the next image row to fill
  for (int64_t i = i0; i < i1; ++i) {
    for (; next <= std::min<int64_t>(H - 1, i + r); ++next) fill(next);
    emit(int(i));
  }
}

// Uninitialised scratch (every element is written before it is read; a zeroing std::vector cost
// ~5 % of the call at 128²).
inline std::unique_ptr<float[]> scratch(int64_t n) { return std::unique_ptr<float[]>(new float[size_t(n)]); }

}  // namespace

// Returns {stats [4] float64 = (loss, L1, SSIM, MSE), grad [H, W, C] float32 = d loss / d x}
// (grad is empty when want_grad is false). Sums are taken per row, then over rows in order, so the
// result does not depend on the number of threads.
std::vector<at::Tensor> forward(const at::Tensor& x_, const at::Tensor& y_, const at::Tensor& window_,
                                double lam, double c1, double c2, bool want_grad) {
  TORCH_CHECK(x_.dim() == 3 && x_.sizes() == y_.sizes(), "image_loss: x and y must be [H, W, C] of one shape");
  TORCH_CHECK(x_.scalar_type() == at::kFloat && y_.scalar_type() == at::kFloat, "image_loss: float32 only");
  const at::Tensor x = x_.contiguous(), y = y_.contiguous(), window = window_.contiguous().to(at::kFloat);
  const int H = int(x.size(0)), W = int(x.size(1)), C = int(x.size(2)), n = W * C, win = int(window.numel());
  TORCH_CHECK(win % 2 == 1 && win <= kMaxWin, "image_loss: the window must have odd length <= 31");
  const float* X = x.data_ptr<float>();
  const float* Y = y.data_ptr<float>();
  const float* g = window.data_ptr<float>();
  const int64_t hn = int64_t(H) * n;
  const double count = double(hn);
  const float C1 = float(c1), C2 = float(c2), gs = float(1.0 / count);

  // Per block of rows: the five statistics (x, y, x², y², x·y) blurred horizontally into a ring, then
  // vertically; the SSIM map A1·A2/(B1·B2) (smgs.metrics.ssim.ssim_from_stats) and, for the gradient,
  // dSSIM/d(μx, E[x²], E[xy]) per pixel (as smgs.train.loss._SSIM.backward), [3][H][n].
  std::vector<double> row_l1(H), row_se(H), row_ssim(H);
  // rows per block: enough that the 2·r rows each block blurs twice (its ends' neighbours) stay few
  const int64_t grain = std::max<int64_t>(std::max(1, 4096 / std::max(n, 1)), 4 * win);
  const auto dm_ = scratch(want_grad ? 3 * hn : 0);
  float* const dm = dm_.get();
  at::parallel_for(0, H, grain, [&](int64_t i0, int64_t i1) {
    std::vector<float> prod(n), pad(n + 2 * (win / 2) * C), st(5 * n), map(n);
    RowRing ring(win, 5, n);
    auto fill = [&](int row) {
      const float* xr = X + int64_t(row) * n;
      const float* yr = Y + int64_t(row) * n;
      if (row >= i0 && row < i1) {   // the block's own rows: their L1 and squared-error sums
        for (int e = 0; e < n; ++e) prod[e] = std::fabs(xr[e] - yr[e]);
        row_l1[row] = row_sum(prod.data(), n);
        for (int e = 0; e < n; ++e) prod[e] = (xr[e] - yr[e]) * (xr[e] - yr[e]);
        row_se[row] = row_sum(prod.data(), n);
      }
      blur_row(xr, ring.row(0, row), pad.data(), n, C, g, win);
      blur_row(yr, ring.row(1, row), pad.data(), n, C, g, win);
      for (int e = 0; e < n; ++e) prod[e] = xr[e] * xr[e];
      blur_row(prod.data(), ring.row(2, row), pad.data(), n, C, g, win);
      for (int e = 0; e < n; ++e) prod[e] = yr[e] * yr[e];
      blur_row(prod.data(), ring.row(3, row), pad.data(), n, C, g, win);
      for (int e = 0; e < n; ++e) prod[e] = xr[e] * yr[e];
      blur_row(prod.data(), ring.row(4, row), pad.data(), n, C, g, win);
    };
    auto emit = [&](int i) {
      for (int m = 0; m < 5; ++m) blur_col(ring, m, st.data() + m * n, i, H, g, win);
      const float *mu1 = st.data(), *mu2 = mu1 + n, *e11 = mu2 + n, *e22 = e11 + n, *e12 = e22 + n;
#pragma omp simd
      for (int e = 0; e < n; ++e) {   // kept branch-free so that it vectorises
        const float s1 = e11[e] - mu1[e] * mu1[e], s2 = e22[e] - mu2[e] * mu2[e];
        const float s12 = e12[e] - mu1[e] * mu2[e];
        const float a1 = 2.f * (mu1[e] * mu2[e]) + C1, a2 = 2.f * s12 + C2;
        const float b1 = mu1[e] * mu1[e] + mu2[e] * mu2[e] + C1, b2 = s1 + s2 + C2;
        const float den = b1 * b2;
        map[e] = a1 * a2 / den;
      }
      row_ssim[i] = row_sum(map.data(), n);
      if (!want_grad) return;
      float* __restrict d0 = dm + int64_t(i) * n;
      float* __restrict d1 = d0 + hn;
      float* __restrict d2 = d1 + hn;
#pragma omp simd
      for (int e = 0; e < n; ++e) {
        const float s1 = e11[e] - mu1[e] * mu1[e], s2 = e22[e] - mu2[e] * mu2[e];
        const float s12 = e12[e] - mu1[e] * mu2[e];
        const float a1 = 2.f * (mu1[e] * mu2[e]) + C1, a2 = 2.f * s12 + C2;
        const float b1 = mu1[e] * mu1[e] + mu2[e] * mu2[e] + C1, b2 = s1 + s2 + C2;
        const float q = gs / (b1 * b2), d_a1 = a2 * q, d_a2 = a1 * q, gm = map[e] * gs;
        const float d_b1 = gm / b1, d_b2 = gm / b2;
        d0[e] = 2.f * ((d_a1 - d_a2) * mu2[e] - (d_b1 - d_b2) * mu1[e]);
        d1[e] = -d_b2;
        d2[e] = 2.f * d_a2;
      }
    };
    stream_rows(i0, i1, H, win, fill, emit);
  });

  double l1 = 0, se = 0, ss = 0;
  for (int i = 0; i < H; ++i) {
    l1 += row_l1[i];
    se += row_se[i];
    ss += row_ssim[i];
  }
  l1 /= count;
  se /= count;
  ss /= count;
  at::Tensor stats = at::empty({4}, at::kDouble);
  double* S = stats.data_ptr<double>();
  S[0] = (1.0 - lam) * l1 + lam * (1.0 - ss);
  S[1] = l1;
  S[2] = ss;
  S[3] = se;
  if (!want_grad) return {stats, at::empty({0}, x.options())};

  // The window is symmetric and zero-padded, so the blur is its own adjoint: blur the three
  // derivative maps, then dSSIM/dx = B(dμ) + 2x·B(dE[x²]) + y·B(dE[xy]). The L1 term's derivative
  // is sign(x − y)/N (0 at x = y, as torch's l1_loss).
  at::Tensor grad = at::empty({H, W, C}, x.options());
  float* G = grad.data_ptr<float>();
  const float wl1 = float((1.0 - lam) / count), wss = float(lam);
  at::parallel_for(0, H, grain, [&](int64_t i0, int64_t i1) {
    std::vector<float> pad(n + 2 * (win / 2) * C), b(3 * n);
    RowRing ring(win, 3, n);
    auto fill = [&](int row) {
      for (int m = 0; m < 3; ++m) blur_row(dm + m * hn + int64_t(row) * n, ring.row(m, row), pad.data(), n, C, g, win);
    };
    auto emit = [&](int i) {
      for (int m = 0; m < 3; ++m) blur_col(ring, m, b.data() + m * n, i, H, g, win);
      const float* xr = X + int64_t(i) * n;
      const float* yr = Y + int64_t(i) * n;
      float* __restrict gr = G + int64_t(i) * n;
#pragma omp simd
      for (int e = 0; e < n; ++e) {
        const float dssim = b[e] + 2.f * xr[e] * b[n + e] + yr[e] * b[2 * n + e];
        const float d = xr[e] - yr[e];
        const float sgn = d > 0.f ? 1.f : (d < 0.f ? -1.f : 0.f);
        gr[e] = wl1 * sgn - wss * dssim;
      }
    };
    stream_rows(i0, i1, H, win, fill, emit);
  });
  return {stats, grad};
}

// The β/γ ray-variance regulariser (smgs.train.loss.ray_variance, same definition): from the
// renderer's per-pixel sums reg [P, 1 + 2R] = (Σw, Σw·v_r, Σw·v_r²), Var_r = mean over the pixels
// with Σw > 0 of max(Σw·v_r²/Σw − μ_r², 0), μ_r = Σw·v_r/Σw. In PyTorch it is ~15 small ops on a
// strided [P, 5] layout (~0.7 ms forward+backward at 128²); here one pass each way.
// Forward: returns var [R] (float32; sums in double). Backward (g [R] given): d Σ_r g_r·Var_r / d reg.
std::vector<at::Tensor> ray_variance(const at::Tensor& reg_, int64_t R, const at::Tensor& g_) {
  TORCH_CHECK(reg_.scalar_type() == at::kFloat && reg_.size(-1) == 1 + 2 * R,
              "ray_variance: reg must be float32 [..., 1 + 2R]");
  const at::Tensor reg = reg_.contiguous();
  const int64_t S = 1 + 2 * R, P = reg.numel() / S;
  const float* q = reg.data_ptr<float>();
  int64_t hits = 0;
  for (int64_t p = 0; p < P; ++p) hits += q[p * S] > 0.f;
  const double n = double(std::max<int64_t>(hits, 1));
  const bool want_grad = g_.defined() && g_.numel() > 0;
  std::vector<double> acc(R, 0.0);
  std::vector<float> gn(R, 0.f);   // dL/dVar_r / n
  at::Tensor grad;
  float* d = nullptr;
  if (want_grad) {
    const at::Tensor g = g_.to(at::kFloat).contiguous();
    for (int64_t r = 0; r < R; ++r) gn[r] = float(double(g.data_ptr<float>()[r]) / n);
    grad = at::zeros_like(reg);
    d = grad.data_ptr<float>();
  }
  for (int64_t p = 0; p < P; ++p) {
    const float* e = q + p * S;
    if (!(e[0] > 0.f)) continue;         // uncovered: contributes 0 (and NaN sums are not hits)
    const float inv = 1.f / e[0];
    float d0 = 0.f;
    for (int64_t r = 0; r < R; ++r) {
      const float mean = e[1 + r] * inv, var = e[1 + R + r] * inv - mean * mean;
      const bool keep = var >= 0.f;       // torch.clamp(min=0) passes at >= 0
      if (!want_grad) {
        if (keep) acc[r] += var;
        continue;
      }
      const float gv = keep ? gn[r] * inv : 0.f;   // dL/dS2
      d0 -= gv * (var - mean * mean);              // dL/dS0 = −gv·(Var − μ²)
      d[p * S + 1 + r] = -2.f * gv * mean;         // dL/dS1 = −2·gv·μ
      d[p * S + 1 + R + r] = gv;
    }
    if (want_grad) d[p * S] = d0;
  }
  if (want_grad) return {grad};
  at::Tensor out = at::empty({R}, reg.options());
  for (int64_t r = 0; r < R; ++r) out.data_ptr<float>()[r] = float(acc[r] / n);
  return {out};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "(1 − λ)·L1 + λ·(1 − SSIM): stats (loss, L1, SSIM, MSE) and d loss / d x");
  m.def("ray_variance", &ray_variance, "β/γ ray variances [R] from reg sums; with g [R], their gradient");
}
