"""A compiled extension, built just in time on first use: the CPU and CUDA renderer backends, and
the CPU projection and training-loss kernels.

One build per process and per ``t_min`` value (a threshold other than the default is compiled in
with ``-DSMGS_T_MIN``); ``smgs.raster.buildcache`` caches the binaries across processes, keyed by
their sources and flags. A missing toolchain (no compiler, no CUDA) or a backend switched off makes
it "not available" with the reason; any other build failure is a ``BuildError`` that stops the
caller: silently falling back to the 100-1000x slower PyTorch reference would change what a run
measures.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any, Callable

from smgs.raster import constants as K

log = logging.getLogger(__name__)


class BuildError(RuntimeError):
    """A compiled extension whose toolchain is present failed to build or load."""


def t_min_define(t_min: float) -> tuple[str, str]:
    """(name suffix, compiler define) of the build for a non-default early-stop threshold."""
    tag = f"{t_min:.3e}".replace(".", "p").replace("-", "m").replace("+", "")
    return f"_tmin{tag}", f"-DSMGS_T_MIN={float(t_min)!r}"


@dataclass
class JitExtension:
    """``build(suffix, defines)`` compiles and loads the module; ``precheck()`` names a missing
    prerequisite cheaply (None if none): that is the only way to be "unavailable". A precheck
    failure is expected on machines without the toolchain and logged at info level when
    ``quiet_precheck``. A failed build raises ``BuildError`` (once built or failed, never retried
    in this process); ``disable`` names the switch that turns the backend off on purpose."""

    kind: str
    build: Callable[[str, tuple[str, ...]], Any]
    precheck: Callable[[], str | None]
    quiet_precheck: bool = False
    what: str = "renderer backend"
    disable: str = ""
    _ext: Any = field(default=None, init=False, repr=False)
    _error: str | None = field(default=None, init=False)
    _failure: BuildError | None = field(default=None, init=False, repr=False)
    _variants: dict[float, Any] = field(default_factory=dict, init=False, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def _build_error(self, exc: Exception) -> BuildError:
        off = (f", or set {self.disable}=1 to run without it (the PyTorch reference is 100-1000x slower)"
               if self.disable else "")
        return BuildError(f"smgs {self.kind} {self.what} failed to build: {type(exc).__name__}: "
                          f"{str(exc).strip()[-3000:]}\nFix the cause above (compiler output, lock, disk){off}.")

    def load(self) -> Any:
        """Build (first time) and load the default module; None, with the reason logged, if a
        prerequisite is missing; ``BuildError`` if the build failed."""
        if self._failure is not None:
            raise self._failure
        if self._ext is not None or self._error is not None:
            return self._ext
        with self._lock:
            if self._failure is not None:
                raise self._failure
            if self._ext is not None or self._error is not None:
                return self._ext
            self._error = self.precheck()
            if self._error is not None:
                log.log(logging.INFO if self.quiet_precheck else logging.WARNING,
                        "smgs %s %s unavailable: %s", self.kind, self.what, self._error)
                return None
            try:
                self._ext = self.build("", ())
            except Exception as exc:  # noqa: BLE001 - re-raised with the cause and the fix
                self._failure = self._build_error(exc)
                self._error = str(self._failure)
                raise self._failure from exc
        return self._ext

    def is_available(self) -> bool:
        """Whether the backend can be used here (builds it on first call). False only for a
        missing prerequisite; a failed build raises ``BuildError``."""
        return self.load() is not None

    def unavailable_reason(self) -> str | None:
        """Why ``is_available()`` is False (None if it is available or was not tried yet)."""
        return self._error

    def loaded(self) -> Any:
        """The default module where this process has loaded it already, else None: never builds."""
        return self._ext

    def module(self, t_min: float = K.T_MIN) -> Any:
        """The loaded module for this threshold (builds it if needed); raises if it cannot be built."""
        ext = self.load()
        if ext is None:
            raise RuntimeError(f"smgs {self.kind} {self.what} unavailable: {self._error}")
        if t_min == K.T_MIN:
            return ext
        with self._lock:
            if t_min not in self._variants:
                suffix, define = t_min_define(t_min)
                try:
                    self._variants[t_min] = self.build(suffix, (define,))
                except Exception as exc:  # noqa: BLE001
                    raise self._build_error(exc) from exc
        return self._variants[t_min]
