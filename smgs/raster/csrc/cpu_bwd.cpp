// Compositing backward of the compiled CPU renderer, the modes without softmax competition (the
// softmax modes, the largest code, build in parallel from cpu_bwd_soft.cpp).
#include "cpu_tiles.h"

namespace smgs {

void backward_tiles(const Scene& sc, const BwdIn& in, float* G, bool gef, bool soft) {
  if (soft) return backward_tiles_soft(sc, in, G, gef);
  if (gef) backward_nch<true, false>(sc, in, G);
  else backward_nch<false, false>(sc, in, G);
}

}  // namespace smgs
