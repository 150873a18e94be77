// A trivial extension for the build-machinery tests (tests/test_raster_build.py): pybind11 only,
// so it compiles in seconds. VALUE comes from the included header, so changing only the header
// must change the build.
#include <pybind11/pybind11.h>

#include "value.h"

#ifndef EXTRA
#define EXTRA 0
#endif

static int answer() { return VALUE + EXTRA; }

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("answer", &answer); }
