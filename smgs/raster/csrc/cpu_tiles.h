// Compositing core of the compiled CPU renderer (threads over tiles: parallel.h) as templates over
// the mode (GEF, SOFT) and the channel count (NCT = 3 keeps the colour state in registers; 0 = any
// count, in scratch). Included only by the core's units (cpu_fwd.cpp, cpu_bwd.cpp, cpu_bwd_soft.cpp).
#pragma once

#include "cpu_core.h"
#include "parallel.h"
#include "simd.h"

namespace smgs {

// ---- blocks ------------------------------------------------------------------------------------------
// A tile of 16x16 pixels is processed as 8 blocks of 8x4 pixels; a block is kNV = 2 vectors of 4x4
// pixels, processed in lockstep over the block's splats: two independent dependency chains per
// splat (the softmax step's chain through the running means is ~200 cycles long, so the loop is
// latency-bound and the second vector comes almost free).
constexpr int kNV = 2;
constexpr int kBW = 4 * kNV;                     // block width in pixels
constexpr int kBX = kTileSize / kBW;             // blocks per tile row
constexpr int kNB = kBX * (kTileSize / 4);       // blocks per tile

// One tile's splats: their packed rows copied into a contiguous per-thread buffer (in tile-list,
// i.e. depth, order; one loop of independent loads instead of a dependent miss per first touch),
// and split into the tile's blocks (a splat goes to the blocks its 3σ box touches).
// Block-list items are positions in the tile list.
struct BlockLists {
  std::vector<float> rows;  // [n, Sp]
  std::vector<int32_t> items;
  int n = 0, Sp = 0;
  int count[kNB];
  const int32_t* list(int b) const { return items.data() + size_t(b) * n; }
};

static void build_block_lists(const Scene& sc, int t, BlockLists& bl) {
  const int off = sc.toff[t];
  const int n = sc.toff[t + 1] - off;
  const int S = sc.S, Sp = padded(S);
  bl.n = n;
  bl.Sp = Sp;
  if (bl.items.size() < size_t(kNB) * n) bl.items.resize(size_t(kNB) * n);
  if (bl.rows.size() < size_t(Sp) * n) bl.rows.resize(size_t(Sp) * n);
  std::fill(bl.count, bl.count + kNB, 0);
  const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
  int32_t* it = bl.items.data();
  float* rows = bl.rows.data();
  const int32_t* tl = sc.tlist + off;
  for (int i = 0; i < n; ++i) std::memcpy(rows + size_t(i) * Sp, sc.pk + size_t(tl[i]) * S, sizeof(float) * S);
  for (int i = 0; i < n; ++i) {
    const int32_t* b = sc.box + 4 * size_t(tl[i]);
    const int bx0 = std::max(b[0] - tx0, 0) / kBW, bx1 = std::min(b[1] - tx0, kTileSize - 1) / kBW;
    const int by0 = std::max(b[2] - ty0, 0) >> 2, by1 = std::min(b[3] - ty0, kTileSize - 1) >> 2;
    for (int by = by0; by <= by1; ++by)
      for (int bx = bx0; bx <= bx1; ++bx) {
        const int k = by * kBX + bx;
        it[size_t(k) * n + bl.count[k]++] = i;
      }
  }
}

// Pixel lanes of a 4x4 block at (x0, y0): lane l is pixel (x0 + l%4, y0 + l/4).
struct Lanes {
  VF px, py;
  VM valid;
  int idx[kLanes];  // pixel index or -1
  SMGS_FI void init(int x0, int y0, int W, int H) {
    alignas(64) float fx[kLanes], fy[kLanes];
    unsigned v = 0;
    for (int l = 0; l < kLanes; ++l) {
      const int x = x0 + (l & 3), y = y0 + (l >> 2);
      fx[l] = float(x) + kPixelCenter;
      fy[l] = float(y) + kPixelCenter;
      const bool in = x < W && y < H;
      v |= unsigned(in) << l;
      idx[l] = in ? y * W + x : -1;
    }
    px = load(fx);
    py = load(fy);
    valid = mask_from_bits(v);
  }
  // gather a per-pixel array (stride, offset); lanes outside the image read `fill`
  VF gather(const float* p, int stride, int off, float fill) const {
    alignas(64) float t[kLanes];
    for (int l = 0; l < kLanes; ++l) t[l] = idx[l] >= 0 ? p[size_t(idx[l]) * stride + off] : fill;
    return load(t);
  }
  void scatter(float* p, int stride, int off, VF x) const {
    alignas(64) float t[kLanes];
    store(t, x);
    for (int l = 0; l < kLanes; ++l)
      if (idx[l] >= 0) p[size_t(idx[l]) * stride + off] = t[l];
  }
};

// Channel storage: in registers when the channel count is a compile-time constant, else in
// per-thread heap scratch.
struct Scratch {
  std::vector<VF> v[4];
  VF* get(int slot, int n) {
    if (v[slot].size() < size_t(n)) v[slot].resize(n);
    return v[slot].data();
  }
};
template <int NCT>
struct Chan {
  VF v[kNV * (NCT + 1)];
  VF* p(Scratch&, int, int) { return v; }
};
template <>
struct Chan<0> {
  VF* p(Scratch& s, int slot, int n) { return s.get(slot, n); }
};

// vanilla_coef for the softmax modes' non-softmax lanes: there wk only matters in a lane's head, and
// a head lane takes the vanilla step only at A = 0, where wk = aT / (0 + aT) = 1 exactly; so no
// division.
SMGS_FI Coef<VF> head_coef(VF T, VF A, VF a) {
  Coef<VF> c;
  c.aT = a * T;
  c.An = A + c.aT;
  c.wk = VF(1.f);
  c.Tn = T * (VF(1.f) - a);
  c.r = VF(1.f);
  return c;
}

// ---- forward ---------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
static int64_t fwd_block(const Scene& sc, const float* rows, int Sp, const int32_t* lst, int n, int x0, int y0,
                         const FwdOut& o, Scratch& scr) {
  constexpr int NV = kNV;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.R;
  Lanes L[NV];
  for (int v = 0; v < NV; ++v) L[v].init(x0 + 4 * v, y0, sc.W, sc.H);
  Chan<NCT> cs;
  VF* C = cs.p(scr, 0, NV * nc);           // C[v * nc + c]; depth is channel nch
  VF* RG = scr.get(1, NV * (1 + 2 * R));   // reg sums per vector: Σw, Σw·v_r, Σw·v_r²
  for (int c = 0; c < NV * nc; ++c) C[c] = VF(0.f);
  for (int c = 0; c < NV * (1 + 2 * R); ++c) RG[c] = VF(0.f);
  VF T[NV], A[NV], dp[NV], pp[NV], cnt[NV], last[NV], dfront[NV];
  VM done[NV];
  for (int v = 0; v < NV; ++v) {
    T[v] = VF(1.f);
    A[v] = dp[v] = pp[v] = cnt[v] = last[v] = dfront[v] = VF(0.f);
    done[v] = mnot(L[v].valid);
  }
  const VF kmaxf(float(sc.kmax));
  const bool need_head = SOFT || R > 0;
  const bool patch = sc.patch;   // a local: stores through the outputs cannot make it reload
  int64_t pairs = 0;
  for (int i = 0; i < n; ++i) {
    const float* s = rows + size_t(lst[i]) * Sp;
    // The early-outs test the splat alone, not `done`: a branch on `done` would wait for the
    // previous splat's whole q -> exp -> T chain before it resolves.
    Quad<VF> k[NV];
    VM inq[NV];
    unsigned anyq = 0;
    for (int v = 0; v < NV; ++v) {
      pairs += popcount(mnot(done[v]));
      k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
      inq[v] = k[v].q <= VF(kQMax);
      anyq |= bits(inq[v]);
    }
    if (!anyq) continue;
    Absorb<VF> ab[NV];
    VM reach[NV];
    unsigned anyr = 0;
    for (int v = 0; v < NV; ++v) {
      ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
      reach[v] = mand(inq[v], ab[v].a >= VF(kAlphaMin));
      anyr |= bits(reach[v]);
    }
    if (!anyr) continue;
    const float d = s[P_D];
    const float* col = s + P_COL;
    bool alldone = true;
    for (int v = 0; v < NV; ++v) {
      VF* Cv = C + v * nc;
      reach[v] = mand(reach[v], mnot(done[v]));
      const VF a = ab[v].a;
      const VF T0 = T[v] * (VF(1.f) - a);
      // the softmax head: the lane's first k_max composited splats, or (patch scope) the tile's
      // first k_max list entries (lst[i] is the tile-list position; exact as a float below 2^24,
      // where k_max is capped). Evaluated only where it is read, so the modes without a head
      // (3dgs and gef_only without the regulariser) keep the loop they had before the scope existed
      // (computed up front it made their forward ~20 % slower, bench/ab.py).
      const auto in_head = [&] { return (patch ? VF(float(lst[i])) : cnt[v]) < kmaxf; };
      // 3DGS: not composited, the pixel is done. Only where the step is vanilla: inside the softmax
      // head a later splat can take the pixel from those before it (constants.T_MIN).
      VM stop = mand(reach[v], T0 < VF(sc.tstop));
      if (SOFT) stop = mand(stop, mnot(in_head()));
      done[v] = mor(done[v], stop);
      const VM rv = mand(reach[v], mnot(stop));
      const VM head = need_head ? mand(rv, in_head()) : rv;
      if (SOFT) {
        const VM soft = mand(head, A[v] > VF(0.f));
        const VF p = -k[v].q;
        Coef<VF> cf = head_coef(T[v], A[v], a);
        if (any(soft)) {
          const SoftFwd<VF> f = softmax_fwd(T[v], A[v], dp[v], pp[v], a, p, d, s[P_BE], s[P_GA], sc.solved);
          cf.Tn = sel(soft, f.T0, cf.Tn);
          cf.An = sel(soft, f.U, cf.An);
          cf.r = sel(soft, f.r, cf.r);
          cf.aT = sel(soft, f.aT, cf.aT);
          cf.wk = sel(soft, f.wk, cf.wk);
        }
        for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] * cf.r + VF(col[c]) * cf.aT, Cv[c]);
        Cv[nch] = sel(rv, Cv[nch] * cf.r + VF(d) * cf.aT, Cv[nch]);
        dp[v] = sel(head, dp[v] + (VF(d) - dp[v]) * cf.wk, dp[v]);
        pp[v] = sel(head, pp[v] + (p - pp[v]) * cf.wk, pp[v]);
        T[v] = sel(rv, cf.Tn, T[v]);
        A[v] = sel(rv, cf.An, A[v]);
      } else {
        const VF aT = a * T[v];
        for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] + VF(col[c]) * aT, Cv[c]);
        Cv[nch] = sel(rv, Cv[nch] + VF(d) * aT, Cv[nch]);
        A[v] = sel(rv, A[v] + aT, A[v]);
        T[v] = sel(rv, T0, T[v]);
      }
      if (R) {  // variance regulariser sums over the first k_max composited splats
        VF* RGv = RG + v * (1 + 2 * R);
        const VM first = mand(head, cnt[v] == VF(0.f));
        dfront[v] = sel(first, VF(d), dfront[v]);
        VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront[v]) / VF(sc.reg_scale));
        w = sel(head, w, VF(0.f));
        RGv[0] = RGv[0] + w;
        for (int r = 0; r < R; ++r) {
          const VF rvv(s[P_COL + nch + r]);
          RGv[1 + r] = RGv[1 + r] + w * rvv;
          RGv[1 + R + r] = RGv[1 + R + r] + w * rvv * rvv;
        }
      }
      cnt[v] = sel(rv, cnt[v] + VF(1.f), cnt[v]);
      last[v] = sel(rv, VF(float(i + 1)), last[v]);
      alldone = alldone && all(done[v]);
    }
    if (alldone) break;
  }
  // outputs
  for (int v = 0; v < NV; ++v) {
    const VF* Cv = C + v * nc;
    for (int c = 0; c < nch; ++c) {
      VF x = Cv[c];
      if (sc.bg) x = x + T[v] * VF(sc.bg[c]);
      L[v].scatter(o.rgb, nch, c, x);
    }
    const VM pos = A[v] > VF(0.f);
    L[v].scatter(o.alpha, 1, 0, A[v]);
    L[v].scatter(o.depth, 1, 0, sel(pos, Cv[nch] / sel(pos, A[v], VF(1.f)), VF(0.f)));
    L[v].scatter(o.Tf, 1, 0, T[v]);
    if (R)
      for (int c = 0; c < 1 + 2 * R; ++c) L[v].scatter(o.reg, 1 + 2 * R, c, RG[v * (1 + 2 * R) + c]);
    alignas(64) float tls[kLanes], tc[kLanes];
    store(tls, last[v]);
    store(tc, cnt[v]);
    for (int l = 0; l < kLanes; ++l)
      if (L[v].idx[l] >= 0) {
        o.last[L[v].idx[l]] = int32_t(tls[l]);
        o.cnt[L[v].idx[l]] = int32_t(tc[l]);
        // `last` counts block-list positions; the tile-list position of the last composited splat
        // is the furthest (the lists are in depth order)
        if (o.lend) o.lend[L[v].idx[l]] = tls[l] > 0.f ? lst[int(tls[l]) - 1] + 1 : 0;
      }
  }
  return pairs;
}

template <bool GEF, bool SOFT, int NCT>
static int64_t forward_impl(const Scene& sc, const FwdOut& o) {
  const int nt = sc.tiles_x * sc.tiles_y;
  const int nw = workers(sc.nthreads, nt);
  std::vector<BlockLists> bl(nw);
  std::vector<Scratch> scr(nw);
  std::vector<int64_t> pairs(nw, 0);
  parallel_dynamic(sc.nthreads, nt, [&](int w, int64_t t) {
    build_block_lists(sc, int(t), bl[w]);
    const int tx0 = int(t % sc.tiles_x) * kTileSize, ty0 = int(t / sc.tiles_x) * kTileSize;
    for (int b = 0; b < kNB; ++b) {
      const int x0 = tx0 + (b % kBX) * kBW, y0 = ty0 + (b / kBX) * 4;
      if (x0 >= sc.W || y0 >= sc.H) continue;
      pairs[w] += fwd_block<GEF, SOFT, NCT>(sc, bl[w].rows.data(), bl[w].Sp, bl[w].list(b), bl[w].count[b], x0, y0,
                                            o, scr[w]);
    }
  });
  int64_t total = 0;
  for (int64_t p : pairs) total += p;
  return total;
}

// ---- backward --------------------------------------------------------------------------------------
// Per-thread scratch for the recomputed softmax heads of one block: one entry per list position
// where some lane composites one of its first k_max splats (so at most 2·16·k_max entries).
struct HeadScratch {
  std::vector<VF> st;  // per entry and vector: T, A, d_past, p_past, C[nc]
  std::vector<int32_t> pos;
  std::vector<uint32_t> mask;  // per entry and vector
  std::vector<SoftFwd<VF>> sf;  // per entry and vector: the softmax step, reused by phase 2
};

// G: gradient rows (stride Sp, pk layout) of this tile's list entries, summed over its blocks.
template <bool GEF, bool SOFT, int NCT>
static void bwd_block(const Scene& sc, const float* rows, int Sp, const int32_t* lst, int n, int x0, int y0,
                      const BwdIn& in, float* G, Scratch& scr, HeadScratch& hs) {
  constexpr int NV = kNV;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.R;
  Lanes L[NV];
  for (int v = 0; v < NV; ++v) L[v].init(x0 + 4 * v, y0, sc.W, sc.H);
  Chan<NCT> cs1, cs2;
  VF* gC = cs1.p(scr, 0, NV * nc);   // adjoint of the colour state (depth is channel nch)
  VF* C1 = cs2.p(scr, 1, NV * nc);   // phase 1 colour state
  VF* gR = scr.get(2, NV * 2 * R);   // dL/d reg sums Σw·v_r and Σw·v_r²
  VF gT[NV], gA[NV], T[NV], last[NV];
  int imax = 0;
  for (int v = 0; v < NV; ++v) {
    // dL/d outputs -> dL/d final state
    const VF Aout = L[v].gather(in.alpha, 1, 0, 0.f);
    const VF dout = L[v].gather(in.depth, 1, 0, 0.f);
    const VF g_alpha = in.g_alpha ? L[v].gather(in.g_alpha, 1, 0, 0.f) : VF(0.f);   // null: no gradient (0)
    const VF g_depth = in.g_depth ? L[v].gather(in.g_depth, 1, 0, 0.f) : VF(0.f);
    gT[v] = VF(0.f);
    for (int c = 0; c < nch; ++c) {
      gC[v * nc + c] = L[v].gather(in.g_rgb, nch, c, 0.f);
      if (sc.bg) gT[v] = gT[v] + gC[v * nc + c] * VF(sc.bg[c]);   // rgb += T·bg
    }
    const VM posA = Aout > VF(0.f);
    const VF Asafe = sel(posA, Aout, VF(1.f));
    gC[v * nc + nch] = sel(posA, g_depth / Asafe, VF(0.f));            // depth = C_d / A
    gA[v] = g_alpha - sel(posA, g_depth * dout / Asafe, VF(0.f));
    T[v] = L[v].gather(in.Tf, 1, 0, 1.f);
    alignas(64) float lastf[kLanes];
    for (int l = 0; l < kLanes; ++l) {
      const int x = L[v].idx[l] >= 0 ? in.last[L[v].idx[l]] : 0;
      lastf[l] = float(x);
      imax = std::max(imax, x);
    }
    last[v] = load(lastf);
  }
  if (imax == 0) return;
  const VF kmaxf(float(sc.kmax));
  const size_t esz = size_t(4 + nc);  // vectors per entry and block vector

  // Phase 1: recompute each lane's head (its first k_max composited splats, or in patch scope its
  // composited splats among the tile's first k_max list entries) front to back, saving the state
  // before every head step (softmax modes) and taking the regulariser's gradients.
  int ne = 0;
  if ((SOFT || R) && sc.kmax > 0) {
    VF T1[NV], A1[NV], dp1[NV], pp1[NV], cnt1[NV], dfront[NV];
    for (int v = 0; v < NV; ++v) {
      T1[v] = VF(1.f);
      A1[v] = dp1[v] = pp1[v] = cnt1[v] = dfront[v] = VF(0.f);
      for (int c = 0; c < nc; ++c) C1[v * nc + c] = VF(0.f);
      for (int r = 0; r < 2 * R; ++r) gR[v * 2 * R + r] = L[v].gather(in.g_reg, 1 + 2 * R, 1 + r, 0.f);
    }
    for (int i = 0; i < imax; ++i) {
      VM hv[NV];
      unsigned anyh = 0;
      for (int v = 0; v < NV; ++v) {
        hv[v] = mand(VF(float(i)) < last[v], (sc.patch ? VF(float(lst[i])) : cnt1[v]) < kmaxf);
        anyh |= bits(hv[v]);
      }
      if (!anyh) break;
      const int j = lst[i];
      const float* s = rows + size_t(j) * Sp;
      Quad<VF> k[NV];
      VM reach[NV];
      unsigned anyq = 0, anyr = 0;
      for (int v = 0; v < NV; ++v) {
        k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
        reach[v] = mand(hv[v], k[v].q <= VF(kQMax));
        anyq |= bits(reach[v]);
      }
      if (!anyq) continue;
      Absorb<VF> ab[NV];
      for (int v = 0; v < NV; ++v) {
        ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
        reach[v] = mand(reach[v], ab[v].a >= VF(kAlphaMin));  // before `last`: composited, never stopped
        anyr |= bits(reach[v]);
      }
      if (!anyr) continue;
      const float d = s[P_D];
      const float* col = s + P_COL;
      if (SOFT) {
        if (hs.pos.size() <= size_t(ne)) {
          hs.pos.resize(ne + 64);
          hs.mask.resize(NV * (ne + 64));
          hs.st.resize((ne + 64) * NV * esz);
          if (SOFT) hs.sf.resize((ne + 64) * NV);
        }
        hs.pos[ne] = i;
        for (int v = 0; v < NV; ++v) {
          VF* e = hs.st.data() + (size_t(ne) * NV + v) * esz;
          e[0] = T1[v];
          e[1] = A1[v];
          e[2] = dp1[v];
          e[3] = pp1[v];
          for (int c = 0; c < nc; ++c) e[4 + c] = C1[v * nc + c];
          hs.mask[ne * NV + v] = bits(reach[v]);
        }
        ++ne;
        for (int v = 0; v < NV; ++v) {
          const VM rv = reach[v];
          if (!any(rv)) continue;
          const VF a = ab[v].a;
          const VM soft = mand(rv, A1[v] > VF(0.f));
          const VF p = -k[v].q;
          Coef<VF> cf = head_coef(T1[v], A1[v], a);
          if (any(soft)) {
            SoftFwd<VF>& f = hs.sf[size_t(ne - 1) * NV + v];
            f = softmax_fwd(T1[v], A1[v], dp1[v], pp1[v], a, p, d, s[P_BE], s[P_GA], sc.solved);
            cf.Tn = sel(soft, f.T0, cf.Tn);
            cf.An = sel(soft, f.U, cf.An);
            cf.r = sel(soft, f.r, cf.r);
            cf.aT = sel(soft, f.aT, cf.aT);
            cf.wk = sel(soft, f.wk, cf.wk);
          }
          VF* Cv = C1 + v * nc;
          for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] * cf.r + VF(col[c]) * cf.aT, Cv[c]);
          Cv[nch] = sel(rv, Cv[nch] * cf.r + VF(d) * cf.aT, Cv[nch]);
          dp1[v] = sel(rv, dp1[v] + (VF(d) - dp1[v]) * cf.wk, dp1[v]);
          pp1[v] = sel(rv, pp1[v] + (p - pp1[v]) * cf.wk, pp1[v]);
          T1[v] = sel(rv, cf.Tn, T1[v]);
          A1[v] = sel(rv, cf.An, A1[v]);
        }
      }
      if (R) {
        float* g = G + size_t(j) * Sp + P_COL + nch;
        for (int v = 0; v < NV; ++v) {
          const VM first = mand(reach[v], cnt1[v] == VF(0.f));
          dfront[v] = sel(first, VF(d), dfront[v]);
          const VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront[v]) / VF(sc.reg_scale));
          for (int r = 0; r < R; ++r) {
            const VF rvv(s[P_COL + nch + r]);
            // reg = Σ w·[1, v, v·v]: d/dv = w·g1 + 2·w·v·g2 (the weights carry no gradient)
            g[r] += hsum(sel(reach[v], w * gR[v * 2 * R + r] + VF(2.f) * w * rvv * gR[v * 2 * R + R + r], VF(0.f)));
          }
        }
      }
      for (int v = 0; v < NV; ++v) cnt1[v] = sel(reach[v], cnt1[v] + VF(1.f), cnt1[v]);
    }
  }

  // Phase 2: back to front over every composited splat.
  VF gdp[NV], gpp[NV];  // adjoints of the running means, non-zero only inside a lane's head
  for (int v = 0; v < NV; ++v) gdp[v] = gpp[v] = VF(0.f);
  int e = ne - 1;
  const VF zero(0.f);
  for (int i = imax - 1; i >= 0; --i) {
    const int j = lst[i];
    const float* s = rows + size_t(j) * Sp;
    Quad<VF> k[NV];
    VM reach[NV];
    unsigned anyq = 0, anyr = 0;
    for (int v = 0; v < NV; ++v) {
      k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
      reach[v] = mand(VF(float(i)) < last[v], k[v].q <= VF(kQMax));
      anyq |= bits(reach[v]);
    }
    if (!anyq) continue;
    Absorb<VF> ab[NV];
    for (int v = 0; v < NV; ++v) {
      ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
      reach[v] = mand(reach[v], ab[v].a >= VF(kAlphaMin));
      anyr |= bits(reach[v]);
    }
    if (!anyr) continue;
    const float d = s[P_D];
    const float* col = s + P_COL;
    const VF* ent = nullptr;
    unsigned hmb[NV] = {};
    if (SOFT && e >= 0 && hs.pos[e] == i) {
      ent = hs.st.data() + size_t(e) * NV * esz;
      for (int v = 0; v < NV; ++v) hmb[v] = hs.mask[e * NV + v];
      --e;
    }
    // per-lane gradients of this splat's parameters, in the pk layout (summed over vectors)
    VF gv[16];
    for (int c = 0; c < 16; ++c) gv[c] = zero;
    for (int v = 0; v < NV; ++v) {
      const VM rv = reach[v];
      if (!any(rv)) continue;
      VF* gCv = gC + v * nc;
      const VF a = ab[v].a;
      const VF p = -k[v].q;
      // state before the step: the 3DGS inverse for tail lanes, the saved state for head lanes
      VF Tpre = T[v] / (VF(1.f) - a);
      VF Apre(0.f), dpre(0.f), ppre(0.f);
      const VM hm = mask_from_bits(hmb[v]);
      const VF* ev = ent ? ent + v * esz : nullptr;
      if (SOFT && hmb[v]) {
        Tpre = sel(hm, ev[0], Tpre);
        Apre = sel(hm, ev[1], Apre);
        dpre = sel(hm, ev[2], dpre);
        ppre = sel(hm, ev[3], ppre);
      }
      VF g_a, g_p(0.f), g_d(0.f), g_be(0.f), g_ga(0.f);
      VF gTn, gAn;
      if (SOFT) {
        const VM soft = mand(hm, Apre > VF(0.f));
        Coef<VF> cf = head_coef(Tpre, Apre, a);
        const bool anysoft = any(soft);
        // phase 1's step of this entry and vector (same inputs): not recomputed
        const SoftFwd<VF>* fp = anysoft ? hs.sf.data() + size_t(e + 1) * NV + v : nullptr;
        if (anysoft) {
          cf.r = sel(soft, fp->r, cf.r);
          cf.aT = sel(soft, fp->aT, cf.aT);
          cf.wk = sel(soft, fp->wk, cf.wk);
        }
        // adjoint of C' = C·r + c·aT (depth is channel nch)
        VF g_r(0.f), g_aT(0.f);
        for (int c = 0; c < nch; ++c) g_aT = g_aT + gCv[c] * VF(col[c]);
        g_aT = g_aT + gCv[nch] * VF(d);
        for (int c = 0; c < nch; ++c) {
          const VF x = sel(rv, gCv[c] * cf.aT, zero);
          if (P_COL + c < 16) gv[P_COL + c] = gv[P_COL + c] + x;
          else G[size_t(j) * Sp + P_COL + c] += hsum(x);
        }
        g_d = gCv[nch] * cf.aT;
        if (anysoft) {
          for (int c = 0; c < nc; ++c) {
            g_r = g_r + gCv[c] * ev[4 + c];
            gCv[c] = sel(soft, gCv[c] * cf.r, gCv[c]);
          }
        }
        // adjoint of the running means d' = d + (d_k - d)·wk, p' likewise (head lanes only)
        const VF g_wk = sel(hm, gdp[v] * (VF(d) - dpre) + gpp[v] * (p - ppre), zero);
        g_d = g_d + sel(hm, gdp[v] * cf.wk, zero);
        g_p = sel(hm, gpp[v] * cf.wk, zero);
        gdp[v] = sel(hm, gdp[v] - gdp[v] * cf.wk, gdp[v]);
        gpp[v] = sel(hm, gpp[v] - gpp[v] * cf.wk, gpp[v]);
        VF gTv, gAv, gav;
        vanilla_coef_bwd(Tpre, Apre, a, gT[v], gA[v], g_aT, g_wk, gTv, gAv, gav);
        gTn = gTv;
        gAn = gAv;
        g_a = gav;
        if (anysoft) {
          const SoftGrad<VF> sg = softmax_bwd(*fp, Tpre, Apre, dpre, ppre, a, p, s[P_BE], s[P_GA], sc.solved,
                                              gT[v], gA[v], g_r, g_aT, g_wk);
          gTn = sel(soft, sg.T, gTn);
          gAn = sel(soft, sg.A, gAn);
          g_a = sel(soft, sg.a, g_a);
          g_p = g_p + sel(soft, sg.p, zero);
          g_d = g_d + sel(soft, sg.d, zero);
          gdp[v] = gdp[v] + sel(soft, sg.dp, zero);
          gpp[v] = gpp[v] + sel(soft, sg.pp, zero);
          g_be = sel(soft, sg.beta, zero);
          g_ga = sel(soft, sg.gamma, zero);
        }
      } else {
        // 3DGS: C' = C + c·aT, A' = A + aT, T' = T(1-a)
        const VF aT = a * Tpre;
        VF g_aT = gA[v];
        for (int c = 0; c < nch; ++c) g_aT = g_aT + gCv[c] * VF(col[c]);
        g_aT = g_aT + gCv[nch] * VF(d);
        for (int c = 0; c < nch; ++c) {
          const VF x = sel(rv, gCv[c] * aT, zero);
          if (P_COL + c < 16) gv[P_COL + c] = gv[P_COL + c] + x;
          else G[size_t(j) * Sp + P_COL + c] += hsum(x);
        }
        g_d = gCv[nch] * aT;
        g_a = g_aT * Tpre - gT[v] * Tpre;
        gTn = g_aT * a + gT[v] * (VF(1.f) - a);
        gAn = gA[v];
      }
      gT[v] = sel(rv, gTn, gT[v]);
      gA[v] = sel(rv, gAn, gA[v]);
      T[v] = sel(rv, Tpre, T[v]);
      const KernGrad<VF> kg =
          splat_kernel_bwd<GEF>(k[v], ab[v], Factor{s[P_CA], s[P_CB], s[P_CC]}, s[P_O], s[P_AL], g_a, g_p);
      gv[P_MX] = gv[P_MX] + sel(rv, kg.mx, zero);
      gv[P_MY] = gv[P_MY] + sel(rv, kg.my, zero);
      gv[P_CA] = gv[P_CA] + sel(rv, kg.ca, zero);
      gv[P_CB] = gv[P_CB] + sel(rv, kg.cb, zero);
      gv[P_CC] = gv[P_CC] + sel(rv, kg.cc, zero);
      gv[P_O] = gv[P_O] + sel(rv, kg.o, zero);
      gv[P_D] = gv[P_D] + sel(rv, g_d, zero);
      if (GEF) gv[P_AL] = gv[P_AL] + sel(rv, kg.alpha, zero);
      if (SOFT) {
        gv[P_BE] = gv[P_BE] + sel(rv, g_be, zero);
        gv[P_GA] = gv[P_GA] + sel(rv, g_ga, zero);
      }
    }
    float* g = G + size_t(j) * Sp;
    store(g, load(g) + reduce16(gv));
  }
}

template <bool GEF, bool SOFT, int NCT>
static void backward_impl(const Scene& sc, const BwdIn& in, float* E) {
  const int nt = sc.tiles_x * sc.tiles_y;
  const int Sp = padded(sc.S);
  const int nw = workers(sc.nthreads, nt);
  std::vector<BlockLists> bl(nw);
  std::vector<Scratch> scr(nw);
  std::vector<HeadScratch> hs(nw);
  parallel_dynamic(sc.nthreads, nt, [&](int w, int64_t t) {
    const int off = sc.toff[t];
    float* G = E + size_t(off) * Sp;
    std::fill(G, G + size_t(sc.toff[t + 1] - off) * Sp, 0.f);
    build_block_lists(sc, int(t), bl[w]);
    const int tx0 = int(t % sc.tiles_x) * kTileSize, ty0 = int(t / sc.tiles_x) * kTileSize;
    for (int b = 0; b < kNB; ++b) {
      const int x0 = tx0 + (b % kBX) * kBW, y0 = ty0 + (b / kBX) * 4;
      if (x0 >= sc.W || y0 >= sc.H) continue;
      bwd_block<GEF, SOFT, NCT>(sc, bl[w].rows.data(), bl[w].Sp, bl[w].list(b), bl[w].count[b], x0, y0, in, G, scr[w],
                                hs[w]);
    }
  });
}

template <bool GEF, bool SOFT>
static int64_t forward_nch(const Scene& sc, const FwdOut& o) {
  return sc.nch == 3 ? forward_impl<GEF, SOFT, 3>(sc, o) : forward_impl<GEF, SOFT, 0>(sc, o);
}
template <bool GEF, bool SOFT>
static void backward_nch(const Scene& sc, const BwdIn& in, float* G) {
  if (sc.nch == 3) backward_impl<GEF, SOFT, 3>(sc, in, G);
  else backward_impl<GEF, SOFT, 0>(sc, in, G);
}

}  // namespace smgs
