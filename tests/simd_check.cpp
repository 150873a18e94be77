// Accuracy of the SIMD layer (smgs/raster/csrc/simd.h) against float64, built and run by
// tests/test_raster_simd.py once per SIMD path the host runs. Prints one line per function:
// "name max_ulp" over a dense sweep of its input range, then the lane-permutation checks.
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <initializer_list>
#include <limits>

#include "simd.h"

using namespace smgs;

// |got - want| in units of the float spacing at want (float64 reference, float32 result).
static double ulp_err(float got, double want) {
  if (std::isnan(want)) return std::isnan(got) ? 0.0 : 1e30;
  if (std::isinf(want)) return (double(got) == want) ? 0.0 : 1e30;
  const float wf = float(want);
  const double ulp = std::nextafter(std::fabs(wf), std::numeric_limits<float>::infinity()) - std::fabs(wf);
  const double u = ulp > 0 ? ulp : std::numeric_limits<float>::denorm_min();
  return std::fabs(double(got) - want) / u;
}

template <class F, class R>
static double sweep(float lo, float hi, int n, F f, R ref) {
  double worst = 0;
  alignas(64) float x[kLanes], y[kLanes];
  for (int i = 0; i < n; i += kLanes) {
    for (int l = 0; l < kLanes; ++l) x[l] = lo + (hi - lo) * float(i + l) / float(n);
    store(y, f(load(x)));
    for (int l = 0; l < kLanes; ++l) {
      const double e = ulp_err(y[l], ref(double(x[l])));
      if (e > worst) worst = e;
    }
  }
  return worst;
}

// log over every binade from the smallest denormal up (dense in each binade)
static double sweep_log() {
  double worst = 0;
  alignas(64) float x[kLanes], y[kLanes];
  for (int e = -149; e < 128; ++e)
    for (int i = 0; i < 4096; i += kLanes) {
      for (int l = 0; l < kLanes; ++l) x[l] = std::ldexp(1.0f + float(i + l) / 4096.0f, e);
      store(y, vlog(load(x)));
      for (int l = 0; l < kLanes; ++l) {
        if (std::isinf(x[l])) continue;
        const double er = ulp_err(y[l], std::log(double(x[l])));
        if (er > worst) worst = er;
      }
    }
  return worst;
}

int main() {
  const int n = 1 << 20;
  std::printf("isa %s\n", kIsaName);
  std::printf("vexp %.3f\n", sweep(-103.0f, 88.7f, n, [](VF v) { return vexp(v); }, [](double x) { return std::exp(x); }));
  std::printf("vexp_kernel %.3f\n", sweep(-80.0f, 0.0f, n, [](VF v) { return vexp(v); }, [](double x) { return std::exp(x); }));
  std::printf("vlog %.3f\n", sweep_log());
  std::printf("vrcp %.3f\n", sweep(1e-30f, 1e30f, n, [](VF v) { return vrcp(v); }, [](double x) { return 1.0 / x; }));
  std::printf("vrcp_unit %.3f\n", sweep(1.0f, 2.0f, n, [](VF v) { return vrcp(v); }, [](double x) { return 1.0 / x; }));
  std::printf("vsqrt_pos %.3f\n", sweep(1.0f, 4.0f, n, [](VF v) { return vsqrt_pos(v); }, [](double x) { return std::sqrt(x); }));
  std::printf("vsqrt %.3f\n", sweep(0.0f, 1e6f, n, [](VF v) { return vsqrt(v); }, [](double x) { return std::sqrt(x); }));
  // special values: exp(-inf-ish) = 0, exp(big) = inf, log(0) = -inf, log(-1) = NaN, NaN propagates
  alignas(64) float x[kLanes], y[kLanes];
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  const float sp[6] = {-200.0f, 200.0f, nan, 0.0f, -1.0f, inf};
  for (int l = 0; l < kLanes; ++l) x[l] = sp[l % 6];
  store(y, vexp(load(x)));
  const bool exp_ok = y[0] == 0.0f && std::isinf(y[1]) && std::isnan(y[2]) && y[3] == 1.0f;
  store(y, vlog(load(x)));
  const bool log_ok = std::isnan(y[2]) && y[3] == -inf && std::isnan(y[4]) && y[5] == inf;
  std::printf("special %d\n", int(exp_ok && log_ok));
  // masks: bits / mask_from_bits / any / all / popcount round trip, sel picks per lane
  bool mask_ok = true;
  for (unsigned b : {0u, 1u, 0x8000u, 0xA5A5u, 0xFFFFu, 0x1234u}) {
    const VM m = mask_from_bits(b);
    mask_ok = mask_ok && bits(m) == b && any(m) == (b != 0) && all(m) == (b == 0xFFFFu) &&
              popcount(m) == __builtin_popcount(b);
    store(y, sel(m, VF(1.0f), VF(2.0f)));
    for (int l = 0; l < kLanes; ++l) mask_ok = mask_ok && y[l] == (((b >> l) & 1u) ? 1.0f : 2.0f);
  }
  std::printf("masks %d\n", int(mask_ok));
  // reduce16: lane k of the result is the lane sum of input k (every lane of every input distinct)
  VF v[kLanes];
  for (int k = 0; k < kLanes; ++k) {
    for (int l = 0; l < kLanes; ++l) x[l] = float(k * 1000 + l * l);
    v[k] = load(x);
  }
  store(y, reduce16(v));
  bool red_ok = true;
  for (int k = 0; k < kLanes; ++k) red_ok = red_ok && y[k] == float(k * 16000 + 1240);
  std::printf("reduce16 %d\n", int(red_ok));
  return 0;
}
