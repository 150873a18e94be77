"""Generic resolution rules for a user's own scene, by name.

Its own module so that the loaders (colmap.py, transforms.py) and the dataset table (datasets.py)
share the rules without importing each other.
"""

from __future__ import annotations

from smgs.data.images import ResolutionRule

CPU_MAX_WIDTH = 400
CPU_LABEL = f"cpu preset: images downscaled to at most {CPU_MAX_WIDTH} px wide; NOT the paper protocol"

# Rules for a user's own COLMAP / transforms.json scene (``dataset=colmap dataset.path=...``).
GENERIC_RULES: dict[str, ResolutionRule] = {
    "native": ResolutionRule("native", label="native resolution"),
    "3dgs": ResolutionRule("3dgs", max_width=1600, label="3DGS -r -1: images wider than 1600 px downscaled to 1600"),
    "paper": ResolutionRule("paper", max_width=1600, label="width 1600 keeping aspect (never upsampled)"),
    "cpu": ResolutionRule("cpu", images="auto", max_width=CPU_MAX_WIDTH, label=CPU_LABEL),
}


def get_generic_rule(name: str) -> ResolutionRule:
    if name not in GENERIC_RULES:
        raise ValueError(f"unknown resolution rule {name!r}; expected one of {', '.join(GENERIC_RULES)}")
    return GENERIC_RULES[name]
