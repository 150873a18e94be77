"""Methods behind one interface, by name: ``create_method("softmax_gs", scene, config)``."""

from baselines.method import CAPABILITIES, Method, MethodSpec, RunSettings, SceneNeeds
from baselines.registry import (BUILTINS, ENTRY_POINT_GROUP, create_method, get_spec, list_methods,
                                merge_config, method_class, register, resolve_config, unregister)

__all__ = ["Method", "MethodSpec", "RunSettings", "SceneNeeds", "CAPABILITIES", "BUILTINS", "ENTRY_POINT_GROUP",
           "create_method", "get_spec", "list_methods", "merge_config", "method_class", "register", "unregister",
           "resolve_config"]
