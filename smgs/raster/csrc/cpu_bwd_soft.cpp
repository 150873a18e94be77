// Compositing backward of the compiled CPU renderer, the softmax modes (see cpu_bwd.cpp).
#include "cpu_tiles.h"

namespace smgs {

void backward_tiles_soft(const Scene& sc, const BwdIn& in, float* G, bool gef) {
  if (gef) backward_nch<true, true>(sc, in, G);
  else backward_nch<false, true>(sc, in, G);
}

}  // namespace smgs
