"""Methods by name, imported lazily.

Lookup order: methods registered in this process (``register``), then the built-ins, then
third-party plugins from the entry-point group ``smgs.methods``. A plugin declares, in its own
package metadata (pyproject ``[project.entry-points."smgs.methods"]``)::

    my_method = "my_pkg.module:MyMethod"      # a Method class, or a MethodSpec object

Listing never imports a method's module (so a CPU machine can list a CUDA-only plugin); the module
is imported when the method is created or its class is asked for.
"""

from __future__ import annotations

import inspect
from importlib import metadata
from typing import TYPE_CHECKING, Any

from baselines.method import METHOD_FUNCTIONS, Method, MethodSpec, Resolved, RunSettings, SceneNeeds, merge_config
from smgs.plugins import entry_points, load_entry_point, load_target, source_of

if TYPE_CHECKING:   # types only: listing the methods imports no torch
    import torch

    from smgs.data.scene import Scene

ENTRY_POINT_GROUP = "smgs.methods"

_SPLAT = "baselines.splatting:GaussianSplatting"

BUILTINS: dict[str, MethodSpec] = {
    "softmax_gs": MethodSpec("softmax_gs", _SPLAT, {"mode": "softmax_gs"}, "Softmax-GS",
                             "GEF sharpness (α) + softmax competition (β, γ)"),
    "3dgs": MethodSpec("3dgs", _SPLAT, {"mode": "3dgs"}, "3D GS", "vanilla 3D Gaussian splatting"),
    "stopthepop": MethodSpec("stopthepop", _SPLAT, {"mode": "3dgs", "sort": "per_pixel"}, "StopThePop",
                             "3DGS compositing, each pixel's splats sorted by their peak depth on its ray"),
    "gef_only": MethodSpec("gef_only", _SPLAT, {"mode": "gef_only"}, "Sharp edge only",
                           "GEF sharpness (α), no softmax competition"),
    "softmax_only": MethodSpec("softmax_only", _SPLAT, {"mode": "softmax_only"}, "Softmax only",
                               "softmax competition (β, γ), no GEF"),
}

_registered: dict[str, MethodSpec] = {}


def register(spec: MethodSpec, overwrite: bool = False) -> None:
    """Register a method in this process (tests, notebooks); overrides built-ins and plugins."""
    if spec.name in _registered and not overwrite:
        raise ValueError(f"method {spec.name!r} is already registered")
    _registered[spec.name] = spec


def unregister(name: str) -> None:
    _registered.pop(name, None)


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return entry_points(ENTRY_POINT_GROUP, BUILTINS, "plugin method")


def list_methods() -> list[str]:
    """Every method name that can be created here (built-ins, registered, plugins), sorted."""
    return sorted(set(BUILTINS) | set(_registered) | set(_entry_points()))


def get_spec(name: str) -> MethodSpec:
    if name in _registered:
        return _registered[name]
    if name in BUILTINS:
        return BUILTINS[name]
    ep = _entry_points().get(name)
    if ep is not None:
        obj = load_entry_point(ep, "method")
        if isinstance(obj, MethodSpec):
            return obj
        return MethodSpec(name, obj, source=source_of(ep))
    raise KeyError(f"unknown method {name!r}; registered methods: {', '.join(list_methods())}")


def method_class(name: str) -> type:
    spec = get_spec(name)
    cls = load_target(spec.target, "method") if isinstance(spec.target, str) else spec.target
    missing = [attr for attr in METHOD_FUNCTIONS if not callable(getattr(cls, attr, None))]
    if missing:
        raise TypeError(f"method {name!r} ({cls!r}) does not implement "
                        f"{', '.join('Method.' + m for m in missing)} (docs/adding-a-method.md, 'Adding a method')")
    return cls


def resolve_config(name: str, config: dict[str, Any] | None = None) -> dict[str, Any]:
    """The method's fixed settings merged with ``config``; a conflict is an error."""
    spec = get_spec(name)
    config = dict(config or {})
    for k, v in spec.fixed.items():
        if k in config and config[k] != v:
            raise ValueError(f"method {name!r} fixes {k}={v!r}; the config asks for {config[k]!r}")
    return merge_config(config, spec.fixed)


def resolve(name: str, config: dict[str, Any] | None = None, run: RunSettings | None = None) -> Resolved:
    """The method's settings for ``run``, worked out once: its config with the fixed settings merged
    (``resolve_config``) and, for a protocol run of a method that gives them, the complete settings
    it trains with (``ResolvedSettings``)."""
    own = resolve_config(name, config)
    fn = getattr(method_class(name), "resolved_settings", None)
    return Resolved(name, own, run, fn(own, run) if callable(fn) and run is not None else None)


def resolved_settings(name: str, config: dict[str, Any] | None, run: RunSettings) -> dict[str, Any] | None:
    """The method's complete settings for ``run`` as plain data (``ResolvedSettings``), or None for
    a method that does not give them."""
    return resolve(name, config, run).data()


def _takes(cls: type, keyword: str) -> bool:
    try:
        params = inspect.signature(cls).parameters.values()
    except (TypeError, ValueError):     # no introspectable signature: let the call decide
        return True
    return any(p.name == keyword or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def _names(cls: type, keyword: str) -> bool:
    """Whether the constructor names ``keyword`` itself (not only through ``**kwargs``)."""
    try:
        return keyword in inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return False


def create_method(name: str, scene: Scene, config: dict[str, Any] | None = None, *,
                  device: torch.device | str, run: RunSettings | None = None,
                  resolved: Resolved | None = None) -> Method:
    """Check the scene against the method's needs, then set the method up on ``device`` (a
    resolved ``torch.device``, or a setting such as "auto", "cpu", "cuda:1", resolved here:
    ``smgs.device.as_device``) for the protocol's ``run`` (None outside a protocol run).
    ``resolved``: the settings already worked out (``resolve``), in place of ``config`` and ``run``;
    a constructor that takes ``settings=`` gets ``resolved.settings`` and builds nothing again."""
    if resolved is None:
        resolved = resolve(name, config, run)
    elif config is not None or run is not None or resolved.name != name:
        raise ValueError(f"create_method({name!r}): give config and run, or the settings resolved for this "
                         f"method (resolved= of {resolved.name!r}), not both")
    from smgs.device import as_device

    dev = as_device(device)
    cls = method_class(name)
    for keyword, why in (("device", "creates its tensors on that device"),
                         ("run", "reads the protocol's steps, seed and budget from it")):
        if not _takes(cls, keyword):
            raise TypeError(f"method {name!r} ({cls.__module__}.{cls.__qualname__}) takes no `{keyword}` "
                            "argument; a method's constructor is __init__(scene, config, *, name, device, run) "
                            f"and {why} (docs/adding-a-method.md, 'Adding a method')")
    needs: SceneNeeds = getattr(cls, "needs", SceneNeeds())
    needs.check(scene, name)
    given = {"settings": resolved.settings} if resolved.settings is not None and _names(cls, "settings") else {}
    method = cls(scene, resolved.config, name=name, device=dev, run=resolved.run, **given)
    if getattr(method, "name", None) != name:
        raise TypeError(f"method {name!r} ({cls.__module__}.{cls.__qualname__}) must set `self.name` to the "
                        f"name it was created under ({name!r}), not {getattr(method, 'name', None)!r}")
    return method
