"""A compiled extension, built just in time on first use: the CPU and CUDA renderer backends, and
the CPU projection and training-loss kernels.

One build per process and per ``t_min`` value (a threshold other than the default is compiled in
with ``-DSMGS_T_MIN``); PyTorch caches the binaries across processes. A backend that cannot be
built is "not available" with the reason, never an import error.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any, Callable

from smgs.raster import constants as K

log = logging.getLogger(__name__)


def t_min_define(t_min: float) -> tuple[str, str]:
    """(name suffix, compiler define) of the build for a non-default early-stop threshold."""
    tag = f"{t_min:.3e}".replace(".", "p").replace("-", "m").replace("+", "")
    return f"_tmin{tag}", f"-DSMGS_T_MIN={float(t_min)!r}"


@dataclass
class JitExtension:
    """``build(suffix, defines)`` compiles and loads the module; ``precheck()`` names a missing
    prerequisite cheaply (None if none). A precheck failure is expected on machines without the
    toolchain and logged at info level when ``quiet_precheck``; a failed build always warns."""

    kind: str
    build: Callable[[str, tuple[str, ...]], Any]
    precheck: Callable[[], str | None]
    quiet_precheck: bool = False
    what: str = "renderer backend"
    _ext: Any = field(default=None, init=False, repr=False)
    _error: str | None = field(default=None, init=False)
    _variants: dict[float, Any] = field(default_factory=dict, init=False, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def load(self) -> Any:
        """Build (first time) and load the default module; None, with the reason logged, if it cannot be."""
        if self._ext is not None or self._error is not None:
            return self._ext
        with self._lock:
            if self._ext is not None or self._error is not None:
                return self._ext
            self._error = self.precheck()
            quiet = self._error is not None and self.quiet_precheck
            if self._error is None:
                try:
                    self._ext = self.build("", ())
                except Exception as exc:  # noqa: BLE001 - any build failure means "not available"
                    self._error = f"{type(exc).__name__}: {str(exc).strip()[-2000:]}"
            if self._error is not None:
                log.log(logging.INFO if quiet else logging.WARNING,
                        "smgs %s %s unavailable: %s", self.kind, self.what, self._error)
        return self._ext

    def is_available(self) -> bool:
        """Whether the backend can be used here (builds it on first call; never raises)."""
        try:
            return self.load() is not None
        except Exception as exc:  # noqa: BLE001
            log.warning("smgs %s %s unavailable: %s", self.kind, self.what, exc)
            return False

    def unavailable_reason(self) -> str | None:
        """Why ``is_available()`` is False (None if it is available or was not tried yet)."""
        return self._error

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
                self._variants[t_min] = self.build(suffix, (define,))
        return self._variants[t_min]
