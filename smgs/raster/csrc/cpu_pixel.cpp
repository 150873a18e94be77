// Per-pixel order on the CPU (sort="per_pixel"): StopThePop's bounded re-sorting window. Each
// pixel walks its tile's list in the global (centre depth) order; every splat that reaches it
// enters a window keyed by its peak depth along the pixel's ray (peak_depth in splat_math.h); when
// the window holds `window` entries its nearest is composited (window 1 is the global order). Equal
// keys leave in arrival, i.e. global, order. A window at least as long as a pixel's list is the
// exact per-pixel sort of smgs/raster/reference.py. One pixel at a time (no SIMD lanes: each pixel
// takes its splats in its own order); the compositing step is fwd_block's (cpu_tiles.h) for one
// pixel. It also gives the leading-splat map (FwdOut::lead) that the view-consistency metric reads,
// in either order (window 1 with zero coefficients is the global order).
//
// Backward, every mode: the forward records each pixel's composited steps (their tile-list
// positions, in its order); the backward replays them through the forward's step (the same code, so
// the same values), keeping the state before each in per-thread scratch; the sweep back to front
// (the adjoints of splat_math.h, as bwd_block in cpu_tiles.h) adds each step's gradients to the row
// of its tile-list entry (cpu_kernel.cpp sums the rows per splat in a fixed order, as for the global
// order), so the gradients do not depend on the thread count. The order carries no gradient.
#include "cpu_core.h"
#include "parallel.h"
#include "pixel_step_bwd.h"

namespace smgs {

namespace {

struct Entry {
  float t, q, a;
  int pos;   // position in the tile's list (its row of pk is lst[pos])
};

struct Pixel {
  float T = 1.f, A = 0.f, dp = 0.f, pp = 0.f;
  int cnt = 0;
  bool done = false;
};

// Whether a step is in the softmax head: the pixel's first k_max composited splats, or (patch scope)
// the tile's first k_max list entries -- in a re-sorted order those need not come first.
inline bool in_head(const Scene& sc, const Pixel& px, int pos) { return (sc.patch ? pos : px.cnt) < sc.kmax; }

// One compositing step of fwd_block (cpu_tiles.h) for one pixel.
template <bool SOFT>
inline void step(const Scene& sc, Pixel& px, float* C, const float* s, const Entry& e) {
  const int nch = sc.nch;
  const float a = e.a, d = s[P_D];
  const float T0 = px.T * (1.f - a);
  const bool head = SOFT && in_head(sc, px, e.pos);
  if (T0 < sc.tstop && !head) {   // vanilla steps only (constants.T_MIN)
    px.done = true;
    return;
  }
  const float* col = s + P_COL;
  if (SOFT) {
    const float p = -e.q;
    Coef<float> cf;
    cf.aT = a * px.T;
    cf.An = px.A + cf.aT;
    cf.wk = 1.f;   // head lanes step vanilla only at A = 0 (head_coef)
    cf.Tn = T0;
    cf.r = 1.f;
    if (head && px.A > 0.f) {
      const SoftFwd<float> f = softmax_fwd(px.T, px.A, px.dp, px.pp, a, p, d, s[P_BE], s[P_GA], sc.solved);
      cf.Tn = f.T0;
      cf.An = f.U;
      cf.r = f.r;
      cf.aT = f.aT;
      cf.wk = f.wk;
    }
    for (int c = 0; c < nch; ++c) C[c] = C[c] * cf.r + col[c] * cf.aT;
    C[nch] = C[nch] * cf.r + d * cf.aT;
    if (head) {
      px.dp = px.dp + (d - px.dp) * cf.wk;
      px.pp = px.pp + (p - px.pp) * cf.wk;
    }
    px.T = cf.Tn;
    px.A = cf.An;
  } else {
    const float aT = a * px.T;
    for (int c = 0; c < nch; ++c) C[c] = C[c] + col[c] * aT;
    C[nch] = C[nch] + d * aT;
    px.A = px.A + aT;
    px.T = T0;
  }
  ++px.cnt;
}

// Hand the window's nearest entry (the first of equal keys) to `take` and remove it.
template <class Take>
inline void pop(std::vector<Entry>& win, Take&& take) {
  size_t m = 0;
  for (size_t k = 1; k < win.size(); ++k)
    if (win[k].t < win[m].t) m = k;
  const Entry e = win[m];
  win.erase(win.begin() + m);   // keeps arrival order among the rest
  take(e);
}

// One pixel's splats in its windowed order: `take(entry)` for each, until it returns false (the
// pixel is done). Returns the pairs evaluated.
template <bool GEF, class Take>
inline int64_t walk_pixel(const Scene& sc, const int32_t* lst, int n, int x, int y, const float* coefs,
                          const float* intr, int window, std::vector<Entry>& win, Take&& take) {
  const float fx = float(x) + kPixelCenter, fy = float(y) + kPixelCenter;
  const float u = (fx - intr[2]) / intr[0], v = (fy - intr[3]) / intr[1];
  win.clear();
  bool live = true;
  int64_t pairs = 0;
  auto pass = [&](const Entry& e) { live = take(e); };
  for (int i = 0; i < n && live; ++i) {
    const int row = lst[i];
    const int32_t* b = sc.box + 4 * size_t(row);
    if (x < b[0] || x > b[1] || y < b[2] || y > b[3]) continue;
    const float* s = sc.pk + size_t(row) * sc.S;
    ++pairs;
    const Quad<float> k = splat_quad(fx, fy, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
    if (!(k.q <= kQMax)) continue;
    const float a = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]).a;
    if (!(a >= kAlphaMin)) continue;
    win.push_back({peak_depth(u, v, coefs + size_t(row) * 9, s[P_D]), k.q, a, i});
    if (int(win.size()) >= window) pop(win, pass);
  }
  while (!win.empty() && live) pop(win, pass);
  return pairs;
}

template <bool GEF, bool SOFT>
int64_t pixel_tiles(const Scene& sc, const FwdOut& o, const float* coefs, const float* intr, int window,
                    std::vector<std::vector<int32_t>>* order) {
  const int nt = sc.tiles_x * sc.tiles_y;
  const int nw = workers(sc.nthreads, nt);
  std::vector<int64_t> pairs(nw, 0);
  parallel_dynamic(sc.nthreads, nt, [&](int w, int64_t t) {
    std::vector<Entry> win;
    win.reserve(window + 1);
    std::vector<float> C(sc.nch + 1);
    const int tx0 = int(t % sc.tiles_x) * kTileSize, ty0 = int(t / sc.tiles_x) * kTileSize;
    const int32_t* lst = sc.tlist + sc.toff[t];
    const int n = sc.toff[t + 1] - sc.toff[t];
    std::vector<int32_t>* taken = order ? &(*order)[t] : nullptr;
    for (int y = ty0; y < std::min(ty0 + kTileSize, sc.H); ++y)
      for (int x = tx0; x < std::min(tx0 + kTileSize, sc.W); ++x) {
        Pixel px;
        int32_t lead[2] = {-1, -1};
        int32_t lend = 0;
        std::fill(C.begin(), C.end(), 0.f);
        pairs[w] += walk_pixel<GEF>(sc, lst, n, x, y, coefs, intr, window, win, [&](const Entry& e) {
          step<SOFT>(sc, px, C.data(), sc.pk + size_t(lst[e.pos]) * sc.S, e);
          if (px.done) return false;
          lend = std::max(lend, int32_t(e.pos + 1));
          if (taken) taken->push_back(e.pos);
          if (o.lead && e.a >= o.lead_alpha && lead[1] < 0) lead[lead[0] < 0 ? 0 : 1] = lst[e.pos];
          return true;
        });
        const size_t pix = size_t(y) * sc.W + x;
        if (o.lead) {
          o.lead[2 * pix] = lead[0];
          o.lead[2 * pix + 1] = lead[1];
        }
        if (o.lend) o.lend[pix] = lend;
        for (int c = 0; c < sc.nch; ++c) o.rgb[pix * sc.nch + c] = C[c] + (sc.bg ? px.T * sc.bg[c] : 0.f);
        o.alpha[pix] = px.A;
        o.depth[pix] = px.A > 0.f ? C[sc.nch] / px.A : 0.f;
        o.Tf[pix] = px.T;
        o.cnt[pix] = px.cnt;
      }
  });
  int64_t total = 0;
  for (int64_t p : pairs) total += p;
  return total;
}

// A composited step of one pixel, for its backward: the tile-list position and the state before it
// (the colour state before it, which only a softmax step's adjoint reads, is kept beside).
struct Taken {
  int pos;
  Pixel pre;
};

// G: gradient rows (stride Sp, pk layout) of the tile-list entries; each tile writes only its own.
// The adjoint of step<SOFT> per composited splat, back to front (pixel_step_bwd.h, as bwd_block in
// cpu_tiles.h).
template <bool GEF, bool SOFT>
void pixel_bwd_tiles(const Scene& sc, const BwdIn& in, float* G, const PixelOrder& order) {
  const int nt = sc.tiles_x * sc.tiles_y;
  const int Sp = padded(sc.S), nch = sc.nch, nc = nch + 1;
  parallel_dynamic(sc.nthreads, nt, [&](int, int64_t t) {
    std::vector<Taken> taken;
    std::vector<float> C(nc), Cpre, gC(nc);
    const int tx0 = int(t % sc.tiles_x) * kTileSize, ty0 = int(t / sc.tiles_x) * kTileSize;
    const int32_t* lst = sc.tlist + sc.toff[t];
    const int n = sc.toff[t + 1] - sc.toff[t];
    float* Gt = G + size_t(sc.toff[t]) * Sp;
    std::fill(Gt, Gt + size_t(n) * Sp, 0.f);
    const int32_t* ord = order.pos + order.off[t];   // the tile's pixels' composited steps, in order
    for (int y = ty0; y < std::min(ty0 + kTileSize, sc.H); ++y)
      for (int x = tx0; x < std::min(tx0 + kTileSize, sc.W); ++x) {
        const size_t pix = size_t(y) * sc.W + x;
        const float fx = float(x) + kPixelCenter, fy = float(y) + kPixelCenter;
        // the forward's steps again, in its order, keeping the state before each
        taken.clear();
        Cpre.clear();
        std::fill(C.begin(), C.end(), 0.f);
        Pixel px;
        for (int m = order.cnt[pix]; m > 0; --m, ++ord) {
          const float* s = sc.pk + size_t(lst[*ord]) * sc.S;
          const Quad<float> q = splat_quad(fx, fy, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
          const float a = splat_absorb<GEF>(q.q, s[P_O], s[P_AL]).a;
          taken.push_back({*ord, px});
          if (SOFT) Cpre.insert(Cpre.end(), C.begin(), C.end());
          step<SOFT>(sc, px, C.data(), s, Entry{0.f, q.q, a, *ord});
        }
        if (taken.empty()) continue;
        // dL/d outputs -> dL/d final state: rgb = C + T·bg, alpha = A, depth = C_d / A
        float gT = 0.f;
        for (int c = 0; c < nch; ++c) {
          gC[c] = in.g_rgb[pix * nch + c];
          if (sc.bg) gT += gC[c] * sc.bg[c];
        }
        const float Aout = in.alpha[pix];
        gC[nch] = Aout > 0.f ? in.g_depth[pix] / Aout : 0.f;
        float gA = in.g_alpha[pix] - (Aout > 0.f ? in.g_depth[pix] * in.depth[pix] / Aout : 0.f);
        float gdp = 0.f, gpp = 0.f;   // adjoints of the running means (softmax head only)
        for (size_t k = taken.size(); k-- > 0;) {
          const int pos = taken[k].pos;
          const Pixel& P = taken[k].pre;
          float* g = Gt + size_t(pos) * Sp;
          const auto pre = [&](int c0, float* h) {   // the channel state before the step (softmax)
            for (int m = 0; m < 4; ++m) h[m] = c0 + m < nc ? Cpre[k * nc + c0 + m] : 0.f;
          };
          pixel_step_bwd<GEF, SOFT>(sc.pk + size_t(lst[pos]) * sc.S, fx, fy, P.T, P.A, P.dp, P.pp,
                                    SOFT && in_head(sc, P, pos), sc.solved, nch, gC, pre,
                                    [&](int col, float v) { g[col] += v; }, gT, gA, gdp, gpp);
        }
      }
  });
}

}  // namespace

int64_t forward_pixel_tiles(const Scene& sc, const FwdOut& o, const float* coefs, const float* intr, int window,
                            bool gef, bool soft, std::vector<std::vector<int32_t>>* order) {
  if (order) order->assign(size_t(sc.tiles_x) * sc.tiles_y, {});
  if (gef) return soft ? pixel_tiles<true, true>(sc, o, coefs, intr, window, order)
                       : pixel_tiles<true, false>(sc, o, coefs, intr, window, order);
  return soft ? pixel_tiles<false, true>(sc, o, coefs, intr, window, order)
              : pixel_tiles<false, false>(sc, o, coefs, intr, window, order);
}

void backward_pixel_tiles(const Scene& sc, const BwdIn& in, float* G, const PixelOrder& order, bool gef, bool soft) {
  if (gef) soft ? pixel_bwd_tiles<true, true>(sc, in, G, order) : pixel_bwd_tiles<true, false>(sc, in, G, order);
  else soft ? pixel_bwd_tiles<false, true>(sc, in, G, order) : pixel_bwd_tiles<false, false>(sc, in, G, order);
}

}  // namespace smgs
