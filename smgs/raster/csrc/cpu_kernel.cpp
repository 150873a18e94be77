// Compiled CPU backend of the smgs renderer: tile binning, depth sort, and compositing forward and
// backward with OpenMP across 16x16 tiles and the 16 pixels of a 4x4 block as SIMD lanes.
//
// Semantics are those of smgs/raster/reference.py; tiling only skips pairs that cannot reach
// (their 3σ box misses the block), so it never changes an image. The per-splat math is in
// splat_math.h, shared with future device backends.
//
// Backward: non-softmax modes and the part of each ray after its first k_max composited splats go
// back to front with the 3DGS trick (T_before = T_after / (1 - a)); the softmax head is recomputed
// per block into per-thread scratch (one entry per list position where some lane composites a
// head splat, so at most 2·16·k_max entries: the state before the step and the step's
// intermediates, which the reverse sweep reads instead of recomputing the step a second time)
// and reversed through the hand-written adjoint. Memory is O(pixels + pairs of tiles) plus that
// per-thread scratch, never pixels × k_max. This file is the torch glue, binning and depth sort; the
// compositing core is cpu_core.h / cpu_tiles.h (SIMD lanes from simd.h).
// The ATen and pybind11 headers these bindings use, not <torch/extension.h>: a third of the build time.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>


#include "cpu_core.h"
#include "parallel.h"

namespace smgs {

// ---- scene preparation: visibility, 3σ boxes, depth order, tile lists ------------------------------

// Pixel range of a splat whose float32 q can be <= 4.5. The float evaluation of
// q = ½(a·dx² + c·dy²) + b·dx·dy has |error| <= γ6·(½(a·dx² + c·dy²) + |b·dx·dy|) (six roundings,
// dx and dy each rounded once), and that sum is <= κ·q with κ = 1 + 2|b|/λmin for a positive-definite
// conic, so q_float <= 4.5 implies q <= 4.5 / (1 - γ6·κ). The box of that ellipse (Σ = conic⁻¹,
// half extents sqrt(2·Qmax·Σxx), sqrt(2·Qmax·Σyy)) is computed in double, with margin. Where no
// such bound exists (non-finite or non-PD conic, κ too large) the splat covers the whole image,
// which is always correct.
static bool splat_box(float mx, float my, float ca, float cb, float cc, int W, int H, int32_t* out) {
  int x0 = 0, x1 = W - 1, y0 = 0, y1 = H - 1;
  bool finite = std::isfinite(mx) && std::isfinite(my) && std::isfinite(ca) && std::isfinite(cb) &&
                std::isfinite(cc);
  double a = ca, b = cb, c = cc;
  double det = a * c - b * b;
  if (finite && a > 0 && c > 0 && det > 0) {
    double lmax = 0.5 * (a + c) + std::sqrt(0.25 * (a - c) * (a - c) + b * b);
    double lmin = det / lmax;
    double kappa = 1.0 + 2.0 * std::fabs(b) / lmin;
    double g = 16.0 * 5.9604644775390625e-8 * kappa;  // 2·γ6 with u = 2^-24
    if (g < 0.5) {
      double qmax = 4.5 / (1.0 - g);
      double rx = std::sqrt(2.0 * qmax * c / det), ry = std::sqrt(2.0 * qmax * a / det);
      double sx = 1e-6 * (1.0 + std::fabs(mx) + rx), sy = 1e-6 * (1.0 + std::fabs(my) + ry);
      // pixel i has its centre at i + 0.5
      double fx0 = std::ceil(mx - rx - sx - 0.5), fx1 = std::floor(mx + rx + sx - 0.5);
      double fy0 = std::ceil(my - ry - sy - 0.5), fy1 = std::floor(my + ry + sy - 0.5);
      if (fx1 < 0 || fy1 < 0 || fx0 > W - 1 || fy0 > H - 1 || fx0 > fx1 || fy0 > fy1) return false;
      x0 = int(std::max(fx0, 0.0));
      x1 = int(std::min(fx1, double(W - 1)));
      y0 = int(std::max(fy0, 0.0));
      y1 = int(std::min(fy1, double(H - 1)));
    }
  }
  out[0] = x0;
  out[1] = x1;
  out[2] = y0;
  out[3] = y1;
  return true;
}

// Sort key of a depth: float bits mapped so unsigned order = numeric order, -0 = +0, NaN last
// (as torch.sort); the index in the low `ib` bits makes the order stable.
static inline uint64_t depth_key(float d, uint32_t i, int ib) {
  uint32_t u;
  if (std::isnan(d)) {
    u = 0xFFFFFFFFu;
  } else {
    if (d == 0.f) d = 0.f;
    std::memcpy(&u, &d, 4);
    u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
  }
  return (uint64_t(u) << ib) | i;
}

// LSD radix sort of 64-bit keys (11-bit digits over the 32 + index_bits meaningful bits); O(n).
static void radix_sort(std::vector<uint64_t>& keys, int index_bits) {
  const int total = 32 + index_bits;
  std::vector<uint64_t> tmp(keys.size());
  std::vector<uint32_t> hist(2048);
  for (int shift = 0; shift < total; shift += 11) {
    std::fill(hist.begin(), hist.end(), 0u);
    for (uint64_t k : keys) hist[(k >> shift) & 2047]++;
    uint32_t sum = 0;
    for (auto& h : hist) {
      uint32_t c = h;
      h = sum;
      sum += c;
    }
    for (uint64_t k : keys) tmp[hist[(k >> shift) & 2047]++] = k;
    keys.swap(tmp);
  }
}

struct Prepared {
  at::Tensor ids, pk, box, toff, tlist, soff, spos;  // soff/spos: each splat's tile-list entries
};

static Prepared prepare(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                        const at::Tensor& colors, const at::Tensor& depths, const at::Tensor& alpha,
                        const at::Tensor& beta, const at::Tensor& gamma, const at::Tensor& regv,
                        int W, int H, int nthreads) {
  const int64_t N = means2d.size(0);
  const int nch = int(colors.size(1));
  const int R = regv.numel() ? int(regv.size(1)) : 0;
  const int S = P_COL + nch + R;
  const float* m2 = means2d.data_ptr<float>();
  const float* cn = conics.data_ptr<float>();
  const float* op = opac.data_ptr<float>();
  const float* dp = depths.data_ptr<float>();
  std::vector<int32_t> box(size_t(4) * N);
  std::vector<char> vis(N);
  parallel_static(nthreads, N, [&](int64_t i) {
    // a <= o·1, so o < 1/255 never reaches (NaN never reaches either)
    vis[i] = (op[i] >= kAlphaMin) &&
             splat_box(m2[2 * i], m2[2 * i + 1], cn[3 * i], cn[3 * i + 1], cn[3 * i + 2], W, H, &box[4 * i]);
  });
  int ib = 1;
  while ((int64_t(1) << ib) < N) ++ib;
  std::vector<uint64_t> keys;
  keys.reserve(N);
  for (int64_t i = 0; i < N; ++i)
    if (vis[i]) keys.push_back(depth_key(dp[i], uint32_t(i), ib));
  radix_sort(keys, ib);
  const uint64_t imask = (uint64_t(1) << ib) - 1;
  const int64_t M = int64_t(keys.size());
  auto i32 = at::TensorOptions().dtype(at::kInt);
  Prepared P;
  P.ids = at::empty({M}, i32);
  P.pk = at::empty({M, S}, at::TensorOptions().dtype(at::kFloat));
  P.box = at::empty({M, 4}, i32);
  int32_t* ids = P.ids.data_ptr<int32_t>();
  float* pk = P.pk.data_ptr<float>();
  int32_t* bx = P.box.data_ptr<int32_t>();
  const float* col = colors.data_ptr<float>();
  const float* al = alpha.numel() ? alpha.data_ptr<float>() : nullptr;
  const float* be = beta.numel() ? beta.data_ptr<float>() : nullptr;
  const float* ga = gamma.numel() ? gamma.data_ptr<float>() : nullptr;
  const float* rv = R ? regv.data_ptr<float>() : nullptr;
  parallel_static(nthreads, M, [&](int64_t j) {
    int64_t i = int64_t(keys[j] & imask);
    ids[j] = int32_t(i);
    float* r = pk + j * S;
    r[P_MX] = m2[2 * i];
    r[P_MY] = m2[2 * i + 1];
    const Factor f = splat_factor(cn[3 * i], cn[3 * i + 1], cn[3 * i + 2]);  // the conic's slots
    r[P_CA] = f.ha;
    r[P_CB] = f.r;
    r[P_CC] = f.hs;
    r[P_O] = op[i];
    r[P_D] = dp[i];
    r[P_AL] = al ? al[i] : 1.f;
    r[P_BE] = be ? be[i] : 0.f;
    r[P_GA] = ga ? ga[i] : 0.f;
    for (int c = 0; c < nch; ++c) r[P_COL + c] = col[i * nch + c];
    for (int c = 0; c < R; ++c) r[P_COL + nch + c] = rv[i * R + c];
    for (int c = 0; c < 4; ++c) bx[4 * j + c] = box[4 * i + c];
  });
  const int tx = (W + kTileSize - 1) / kTileSize, ty = (H + kTileSize - 1) / kTileSize;
  P.toff = at::zeros({int64_t(tx) * ty + 1}, i32);
  int32_t* toff = P.toff.data_ptr<int32_t>();
  int64_t L = 0;
  for (int64_t j = 0; j < M; ++j) {
    const int32_t* b = bx + 4 * j;
    for (int y = b[2] / kTileSize; y <= b[3] / kTileSize; ++y)
      for (int x = b[0] / kTileSize; x <= b[1] / kTileSize; ++x) toff[y * tx + x + 1]++;
  }
  for (int t = 0; t < tx * ty; ++t) toff[t + 1] += toff[t];
  L = toff[tx * ty];
  P.tlist = at::empty({L}, i32);
  P.soff = at::empty({M + 1}, i32);
  P.spos = at::empty({L}, i32);
  int32_t* tl = P.tlist.data_ptr<int32_t>();
  int32_t* soff = P.soff.data_ptr<int32_t>();
  int32_t* spos = P.spos.data_ptr<int32_t>();
  std::vector<int32_t> fill(toff, toff + tx * ty);
  int32_t k = 0;
  for (int64_t j = 0; j < M; ++j) {  // in depth order, so every tile list is depth-ordered
    const int32_t* b = bx + 4 * j;
    soff[j] = k;
    for (int y = b[2] / kTileSize; y <= b[3] / kTileSize; ++y)
      for (int x = b[0] / kTileSize; x <= b[1] / kTileSize; ++x) {
        spos[k++] = fill[y * tx + x];
        tl[fill[y * tx + x]++] = int32_t(j);
      }
  }
  soff[M] = k;
  return P;
}

static void check_f32(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous(), name,
              " must be a contiguous float32 CPU tensor");
}

static Scene make_scene(const at::Tensor& pk, const at::Tensor& box, const at::Tensor& toff,
                        const at::Tensor& tlist, const at::Tensor& bg, int W, int H, int nch, int R,
                        int64_t kmax, bool solved, double reg_scale, int nthreads, double t_min, bool patch) {
  Scene sc;
  sc.W = W;
  sc.H = H;
  sc.nch = nch;
  sc.R = R;
  sc.S = P_COL + nch + R;
  sc.M = int(pk.size(0));
  sc.tiles_x = (W + kTileSize - 1) / kTileSize;
  sc.tiles_y = (H + kTileSize - 1) / kTileSize;
  sc.kmax = int(std::min<int64_t>(kmax, int64_t(1) << 24));  // float lane counters are exact to 2^24
  sc.patch = patch;
  sc.solved = solved;
  sc.reg_scale = float(reg_scale);
  sc.pk = pk.data_ptr<float>();
  sc.box = box.data_ptr<int32_t>();
  sc.toff = toff.data_ptr<int32_t>();
  sc.tlist = tlist.data_ptr<int32_t>();
  sc.bg = bg.numel() ? bg.data_ptr<float>() : nullptr;
  sc.nthreads = std::max(1, nthreads);
  sc.tstop = float(t_min * (1.0 - kTStopSlack));  // formed in double, as constants.py does
  return sc;
}

// Per splat the sum of its tile-list entries' gradient rows E [L, padded(S)], in a fixed order (so
// gradients do not depend on the number of threads), back in input order: dL/d[means2d, conics,
// opacities, colors, depths, alpha, beta, gamma, reg_values] over the N input splats (zeros for
// splats that reach no pixel).
static std::vector<at::Tensor> splat_grads(const at::Tensor& E, const at::Tensor& ids, const at::Tensor& soff,
                                           const at::Tensor& spos, int64_t N, int nch, int R, int M, int S,
                                           int nthreads) {
  const int Sp = padded(S);
  auto f32 = at::TensorOptions().dtype(at::kFloat);
  at::Tensor gm = at::zeros({N, 2}, f32), gc = at::zeros({N, 3}, f32), go = at::zeros({N}, f32),
                gcol = at::zeros({N, nch}, f32), gd = at::zeros({N}, f32), gal = at::zeros({N}, f32),
                gbe = at::zeros({N}, f32), gga = at::zeros({N}, f32), grv = at::zeros({N, R}, f32);
  const float* Ep = E.data_ptr<float>();
  const int32_t* id = ids.data_ptr<int32_t>();
  const int32_t* so = soff.data_ptr<int32_t>();
  const int32_t* sp = spos.data_ptr<int32_t>();
  float *pm = gm.data_ptr<float>(), *pc = gc.data_ptr<float>(), *po = go.data_ptr<float>(),
        *pcol = gcol.data_ptr<float>(), *pd = gd.data_ptr<float>(), *pal = gal.data_ptr<float>(),
        *pbe = gbe.data_ptr<float>(), *pga = gga.data_ptr<float>(), *prv = R ? grv.data_ptr<float>() : nullptr;
    // contiguous chunks of splats, one gradient row of scratch per chunk
  parallel_dynamic(nthreads, (M + 4095) / 4096, [&](int, int64_t chunk) {
    std::vector<float> r(S);
    for (int j = int(chunk) * 4096, je = std::min(M, j + 4096); j < je; ++j) {
      std::fill(r.begin(), r.end(), 0.f);
      for (int k = so[j]; k < so[j + 1]; ++k) {
        const float* e = Ep + size_t(sp[k]) * Sp;
        for (int c = 0; c < S; ++c) r[c] += e[c];
      }
      const int64_t i = id[j];  // rows are in depth order; back to input order
      pm[2 * i] = r[P_MX];
      pm[2 * i + 1] = r[P_MY];
      pc[3 * i] = r[P_CA];
      pc[3 * i + 1] = r[P_CB];
      pc[3 * i + 2] = r[P_CC];
      po[i] = r[P_O];
      pd[i] = r[P_D];
      pal[i] = r[P_AL];
      pbe[i] = r[P_BE];
      pga[i] = r[P_GA];
      for (int c = 0; c < nch; ++c) pcol[i * nch + c] = r[P_COL + c];
      for (int c = 0; c < R; ++c) prv[i * R + c] = r[P_COL + nch + c];
    }
  });
  return {gm, gc, go, gcol, gd, gal, gbe, gga, grv};
}

// The splat inputs both forwards take: float32, contiguous, fewer than 2^24 splats.
static void check_splats(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opac,
                         const at::Tensor& colors, const at::Tensor& depths, const at::Tensor& alpha,
                         const at::Tensor& beta, const at::Tensor& gamma, const at::Tensor& bg, bool gef,
                         bool soft) {
  check_f32(means2d, "means2d");
  check_f32(conics, "conics");
  check_f32(opac, "opacities");
  check_f32(colors, "colors");
  check_f32(depths, "depths");
  TORCH_CHECK(means2d.size(0) < (int64_t(1) << 24), "the cpu backend handles fewer than 2^24 splats");
  if (gef) check_f32(alpha, "alpha");
  if (soft) {
    check_f32(beta, "beta");
    check_f32(gamma, "gamma");
  }
  if (bg.numel()) check_f32(bg, "background");
}

// Returns [rgb, alpha, depth, reg, n_contrib, T_final, last, pairs, ids, pk, box, tile_off, tile_list,
// splat_off, splat_pos, list_end]. patch: the k_max scope (Scene::patch); list_end [H, W]: 1 + the
// furthest tile-list position each pixel composited (FwdOut::lend).
std::vector<at::Tensor> forward(at::Tensor means2d, at::Tensor conics, at::Tensor opac,
                                   at::Tensor colors, at::Tensor depths, at::Tensor alpha,
                                   at::Tensor beta, at::Tensor gamma, at::Tensor bg, at::Tensor regv,
                                   int64_t W, int64_t H, bool gef, bool soft, int64_t kmax, bool solved,
                                   double reg_scale, int64_t nthreads, double t_min, bool patch) {
  check_splats(means2d, conics, opac, colors, depths, alpha, beta, gamma, bg, gef, soft);
  if (regv.numel()) check_f32(regv, "reg_values");
  const int nch = int(colors.size(1));
  const int R = regv.numel() ? int(regv.size(1)) : 0;
  Prepared P = prepare(means2d, conics, opac, colors, depths, alpha, beta, gamma, regv, int(W), int(H), int(nthreads));
  Scene sc = make_scene(P.pk, P.box, P.toff, P.tlist, bg, int(W), int(H), nch, R, kmax, solved, reg_scale,
                        int(nthreads), t_min, patch);
  auto f32 = at::TensorOptions().dtype(at::kFloat);
  auto i32 = at::TensorOptions().dtype(at::kInt);
  at::Tensor rgb = at::empty({H, W, nch}, f32), a = at::empty({H, W}, f32), dep = at::empty({H, W}, f32),
                Tf = at::empty({H, W}, f32), reg = at::empty({H, W, R ? 1 + 2 * R : 0}, f32),
                last = at::empty({H, W}, i32), cnt = at::empty({H, W}, i32), lend = at::empty({H, W}, i32);
  FwdOut o{rgb.data_ptr<float>(), a.data_ptr<float>(), dep.data_ptr<float>(), Tf.data_ptr<float>(),
           R ? reg.data_ptr<float>() : nullptr, last.data_ptr<int32_t>(), cnt.data_ptr<int32_t>(),
           lend.data_ptr<int32_t>()};
  int64_t pairs = forward_tiles(sc, o, gef, soft);
  at::Tensor tp = at::full({1}, pairs, at::TensorOptions().dtype(at::kLong));
  return {rgb, a, dep, reg, cnt, Tf, last, tp, P.ids, P.pk, P.box, P.toff, P.tlist, P.soff, P.spos, lend};
}

// sort="per_pixel" (cpu_pixel.cpp). coefs [N, 9] (smgs/raster/ray_depth.py), intr (fx, fy, cx, cy).
// Returns [rgb, alpha, depth, n_contrib, T_final, pairs, ids, pk, box, tile_off, tile_list, splat_off,
// splat_pos, order, order_off, leaders, list_end]: with keep_order the pixels' composited steps
// (PixelOrder in cpu_core.h; else empty), which backward_pixel reads with the tensors after `pairs`;
// with lead_alpha >= 0, leaders [H, W, 2]: each pixel's first two composited splats with
// a >= lead_alpha (input indices, -1 where fewer; else empty); list_end as forward's.
std::vector<at::Tensor> forward_pixel(at::Tensor means2d, at::Tensor conics, at::Tensor opac, at::Tensor colors,
                                      at::Tensor depths, at::Tensor alpha, at::Tensor beta, at::Tensor gamma,
                                      at::Tensor bg, at::Tensor coefs, at::Tensor intr, int64_t W, int64_t H,
                                      bool gef, bool soft, int64_t kmax, bool solved, int64_t nthreads,
                                      double t_min, int64_t window, bool keep_order, double lead_alpha,
                                      bool patch) {
  check_splats(means2d, conics, opac, colors, depths, alpha, beta, gamma, bg, gef, soft);
  check_f32(coefs, "coefs");
  check_f32(intr, "intrinsics");
  const int64_t N = means2d.size(0);
  TORCH_CHECK(coefs.dim() == 2 && coefs.size(0) == N && coefs.size(1) == 9, "coefs must be [N, 9]");
  TORCH_CHECK(intr.numel() == 4, "intrinsics must be (fx, fy, cx, cy)");
  TORCH_CHECK(window >= 1, "window must be >= 1");
  const int nch = int(colors.size(1));
  const at::Tensor none = at::empty({0}, at::TensorOptions().dtype(at::kFloat));
  Prepared P = prepare(means2d, conics, opac, colors, depths, alpha, beta, gamma, none, int(W), int(H), int(nthreads));
  Scene sc = make_scene(P.pk, P.box, P.toff, P.tlist, bg, int(W), int(H), nch, 0, kmax, solved, 1.0, int(nthreads),
                        t_min, patch);
  // the coefficients in pk row (depth) order
  const int64_t M = P.ids.numel();
  std::vector<float> cs(size_t(M) * 9);
  const int32_t* ids = P.ids.data_ptr<int32_t>();
  const float* cf = coefs.data_ptr<float>();
  for (int64_t j = 0; j < M; ++j) std::memcpy(&cs[size_t(j) * 9], cf + size_t(ids[j]) * 9, sizeof(float) * 9);
  auto f32 = at::TensorOptions().dtype(at::kFloat);
  auto i32 = at::TensorOptions().dtype(at::kInt);
  at::Tensor rgb = at::empty({H, W, nch}, f32), a = at::empty({H, W}, f32), dep = at::empty({H, W}, f32),
             Tf = at::empty({H, W}, f32), cnt = at::empty({H, W}, i32), lend = at::empty({H, W}, i32);
  FwdOut o{rgb.data_ptr<float>(), a.data_ptr<float>(), dep.data_ptr<float>(), Tf.data_ptr<float>(), nullptr,
           nullptr, cnt.data_ptr<int32_t>(), lend.data_ptr<int32_t>()};
  const bool lead = lead_alpha >= 0.0;
  at::Tensor leaders = lead ? at::empty({H, W, 2}, i32) : at::empty({0}, i32);
  if (lead) {
    o.lead = leaders.data_ptr<int32_t>();
    o.lead_alpha = float(lead_alpha);
  }
  std::vector<std::vector<int32_t>> order;
  int64_t pairs = forward_pixel_tiles(sc, o, cs.data(), intr.data_ptr<float>(), int(window), gef, soft,
                                      keep_order ? &order : nullptr);
  // the tiles' records one after another
  at::Tensor ooff = at::zeros({int64_t(order.size()) + 1}, at::TensorOptions().dtype(at::kLong));
  int64_t* op = ooff.data_ptr<int64_t>();
  for (size_t t = 0; t < order.size(); ++t) op[t + 1] = op[t] + int64_t(order[t].size());
  at::Tensor opos = at::empty({op[order.size()]}, i32);
  for (size_t t = 0; t < order.size(); ++t)
    std::copy(order[t].begin(), order[t].end(), opos.data_ptr<int32_t>() + op[t]);
  if (lead) {   // pk rows -> input indices
    int32_t* l = leaders.data_ptr<int32_t>();
    for (int64_t k = 0; k < 2 * H * W; ++k)
      if (l[k] >= 0) l[k] = ids[l[k]];
  }
  return {rgb, a, dep, cnt, Tf, at::full({1}, pairs, at::TensorOptions().dtype(at::kLong)), P.ids, P.pk, P.box,
          P.toff, P.tlist, P.soff, P.spos, opos, ooff, leaders, lend};
}

// Backward of forward_pixel (kept with keep_order): its recorded order replayed. Returns the
// gradients as backward does (reg_values: none).
std::vector<at::Tensor> backward_pixel(at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth, at::Tensor alpha_out,
                                       at::Tensor depth_out, at::Tensor cnt, at::Tensor ids, at::Tensor pk,
                                       at::Tensor box, at::Tensor toff, at::Tensor tlist, at::Tensor soff,
                                       at::Tensor spos, at::Tensor order, at::Tensor order_off, at::Tensor bg,
                                       int64_t N, int64_t nch, int64_t W, int64_t H, bool gef, bool soft, int64_t kmax,
                                       bool solved, int64_t nthreads, double t_min, bool patch) {
  check_f32(g_rgb, "grad rgb");
  check_f32(g_alpha, "grad alpha");
  check_f32(g_depth, "grad depth");
  TORCH_CHECK(order_off.numel() == toff.numel(), "backward_pixel needs the order of a forward_pixel with keep_order");
  Scene sc = make_scene(pk, box, toff, tlist, bg, int(W), int(H), int(nch), 0, kmax, solved, 1.0, int(nthreads),
                        t_min, patch);
  at::Tensor E = at::empty({tlist.numel(), padded(sc.S)}, at::TensorOptions().dtype(at::kFloat));
  BwdIn in{g_rgb.data_ptr<float>(), g_alpha.data_ptr<float>(), g_depth.data_ptr<float>(), nullptr,
           alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(), nullptr, nullptr};
  const PixelOrder po{order.data_ptr<int32_t>(), order_off.data_ptr<int64_t>(), cnt.data_ptr<int32_t>()};
  backward_pixel_tiles(sc, in, E.data_ptr<float>(), po, gef, soft);
  return splat_grads(E, ids, soff, spos, N, int(nch), 0, sc.M, sc.S, int(nthreads));
}

// Returns dL/d[means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values] over the N
// input splats (zeros for splats that reach no pixel). An empty g_alpha or g_depth is an output the
// loss did not use (zero gradient, never made: the trainer's loss reads the colours only).
std::vector<at::Tensor> backward(at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth,
                                    at::Tensor g_reg, at::Tensor alpha_out, at::Tensor depth_out,
                                    at::Tensor Tf, at::Tensor last, at::Tensor ids, at::Tensor pk,
                                    at::Tensor box, at::Tensor toff, at::Tensor tlist, at::Tensor soff,
                                    at::Tensor spos, at::Tensor bg,
                                    int64_t N, int64_t nch, int64_t R, int64_t W, int64_t H, bool gef, bool soft,
                                    int64_t kmax, bool solved, double reg_scale, int64_t nthreads, bool patch) {
  check_f32(g_rgb, "grad rgb");
  const bool has_alpha = g_alpha.numel() != 0, has_depth = g_depth.numel() != 0;
  if (has_alpha) check_f32(g_alpha, "grad alpha");
  if (has_depth) check_f32(g_depth, "grad depth");
  if (R) check_f32(g_reg, "grad reg");
  Scene sc = make_scene(pk, box, toff, tlist, bg, int(W), int(H), int(nch), int(R), kmax, solved, reg_scale,
                        int(nthreads), kTMin, patch);  // t_min is in `last`: the backward never tests it
  const int S = sc.S;
  // one gradient row per tile-list entry (each tile fills its own rows), then per splat the sum
  // over its tiles in a fixed order: gradients do not depend on the number of threads
  const int Sp = padded(S);
  at::Tensor E = at::empty({tlist.numel(), Sp}, at::TensorOptions().dtype(at::kFloat));
  BwdIn in{g_rgb.data_ptr<float>(), has_alpha ? g_alpha.data_ptr<float>() : nullptr,
           has_depth ? g_depth.data_ptr<float>() : nullptr, R ? g_reg.data_ptr<float>() : nullptr, alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(),
           Tf.data_ptr<float>(), last.data_ptr<int32_t>()};
  backward_tiles(sc, in, E.data_ptr<float>(), gef, soft);
  return splat_grads(E, ids, soff, spos, N, int(nch), int(R), sc.M, sc.S, int(nthreads));
}

// Constants as compiled, for the test that they mirror smgs/raster/constants.py.
std::vector<double> constants() {
  return {kAlphaMax, kAlphaMin, kTMin, kQMax, kExpArgMax, kDecayArgMax, kPixelCenter, double(kTileSize), kTStop, kTiny};
}

// The SIMD path compiled in (simd.h): avx512, avx2, neon or scalar.
std::string isa() { return simd_isa(); }

}  // namespace smgs

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &smgs::forward, "smgs CPU splat compositing, forward");
  m.def("backward", &smgs::backward, "smgs CPU splat compositing, backward");
  m.def("forward_pixel", &smgs::forward_pixel, "smgs CPU splat compositing in per-pixel order, forward");
  m.def("backward_pixel", &smgs::backward_pixel, "smgs CPU splat compositing in per-pixel order, backward");
  m.def("constants", &smgs::constants, "numeric conventions as compiled");
  m.def("isa", &smgs::isa, "the SIMD path compiled in");
}
