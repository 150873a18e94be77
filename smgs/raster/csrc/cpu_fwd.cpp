// Compositing forward of the compiled CPU renderer, every mode (see cpu_tiles.h).
#include "cpu_tiles.h"

namespace smgs {

int64_t forward_tiles(const Scene& sc, const FwdOut& o, bool gef, bool soft) {
  if (gef) return soft ? forward_nch<true, true>(sc, o) : forward_nch<true, false>(sc, o);
  return soft ? forward_nch<false, true>(sc, o) : forward_nch<false, false>(sc, o);
}

const char* simd_isa() { return kIsaName; }

}  // namespace smgs
