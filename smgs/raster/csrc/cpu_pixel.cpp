// Per-pixel order on the CPU (sort="per_pixel"), forward only: StopThePop's bounded re-sorting
// window. Each pixel walks its tile's list in the global (centre depth) order; every splat that
// reaches it enters a window keyed by its peak depth along the pixel's ray (peak_depth in
// splat_math.h); when the window holds `window` entries its nearest is composited (window 1 is the
// global order). Equal keys
// leave in arrival, i.e. global, order. A window at least as long as a pixel's list is the exact
// per-pixel sort of smgs/raster/reference.py. One pixel at a time (no SIMD lanes: each pixel takes
// its splats in its own order); the compositing step is fwd_block's (cpu_tiles.h) for one pixel.
#include "cpu_core.h"
#include "parallel.h"

namespace smgs {

namespace {

struct Entry {
  float t, q, a;
  int row;
};

struct Pixel {
  float T = 1.f, A = 0.f, dp = 0.f, pp = 0.f;
  int cnt = 0;
  bool done = false;
};

// One compositing step of fwd_block (cpu_tiles.h) for one pixel.
template <bool SOFT>
inline void step(const Scene& sc, Pixel& px, float* C, const float* s, const Entry& e) {
  const int nch = sc.nch;
  const float a = e.a, d = s[P_D];
  const float T0 = px.T * (1.f - a);
  if (T0 < sc.tstop && (!SOFT || px.cnt >= sc.kmax)) {   // vanilla steps only (constants.T_MIN)
    px.done = true;
    return;
  }
  const float* col = s + P_COL;
  if (SOFT) {
    const bool head = px.cnt < sc.kmax;
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

// Composite the window's nearest entry (the first of equal keys) and remove it.
template <bool SOFT>
inline void pop(const Scene& sc, Pixel& px, float* C, std::vector<Entry>& win) {
  size_t m = 0;
  for (size_t k = 1; k < win.size(); ++k)
    if (win[k].t < win[m].t) m = k;
  const Entry e = win[m];
  win.erase(win.begin() + m);   // keeps arrival order among the rest
  step<SOFT>(sc, px, C, sc.pk + size_t(e.row) * sc.S, e);
}

template <bool GEF, bool SOFT>
int64_t pixel_tiles(const Scene& sc, const FwdOut& o, const float* coefs, const float* intr, int window) {
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
    for (int y = ty0; y < std::min(ty0 + kTileSize, sc.H); ++y)
      for (int x = tx0; x < std::min(tx0 + kTileSize, sc.W); ++x) {
        const float fx = float(x) + kPixelCenter, fy = float(y) + kPixelCenter;
        const float u = (fx - intr[2]) / intr[0], v = (fy - intr[3]) / intr[1];
        Pixel px;
        std::fill(C.begin(), C.end(), 0.f);
        win.clear();
        for (int i = 0; i < n && !px.done; ++i) {
          const int row = lst[i];
          const int32_t* b = sc.box + 4 * size_t(row);
          if (x < b[0] || x > b[1] || y < b[2] || y > b[3]) continue;
          const float* s = sc.pk + size_t(row) * sc.S;
          ++pairs[w];
          const Quad<float> k = splat_quad(fx, fy, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
          if (!(k.q <= kQMax)) continue;
          const float a = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]).a;
          if (!(a >= kAlphaMin)) continue;
          win.push_back({peak_depth(u, v, coefs + size_t(row) * 9, s[P_D]), k.q, a, row});
          if (int(win.size()) >= window) pop<SOFT>(sc, px, C.data(), win);
        }
        while (!win.empty() && !px.done) pop<SOFT>(sc, px, C.data(), win);
        const size_t pix = size_t(y) * sc.W + x;
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

}  // namespace

int64_t forward_pixel_tiles(const Scene& sc, const FwdOut& o, const float* coefs, const float* intr, int window,
                            bool gef, bool soft) {
  if (gef) return soft ? pixel_tiles<true, true>(sc, o, coefs, intr, window)
                       : pixel_tiles<true, false>(sc, o, coefs, intr, window);
  return soft ? pixel_tiles<false, true>(sc, o, coefs, intr, window)
              : pixel_tiles<false, false>(sc, o, coefs, intr, window);
}

}  // namespace smgs
