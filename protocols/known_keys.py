"""No setting is silently ignored: a command-line key that nothing reads is refused before anything
runs, naming the nearest key that exists.

Hydra refuses ``steps=30`` (no such key) and suggests ``+steps=30``, which adds a key that nothing
reads: the run went on with the preset's step count. The known keys are not listed by hand:

- a key of the composed config (configs/config.yaml and the groups the command line picks, so a
  key added to a YAML file is known at once), or a key below a mapping the config leaves open
  (``{}``: ``grid.seeds_of``, a plugin method's ``train``), whose keys are the reader's to name;
- a key of a section that checks its own keys against its type (``CHECKED_SECTIONS``): those
  refuse an unknown key with the nearest themselves, before any cell runs (the dataclasses of
  ``protocols.sections`` and ``smgs.train.config`` through ``from_dict``, a scene format's fields,
  the renderer's axes), including the keys a plugin strategy or scene format adds.
"""

from __future__ import annotations

import difflib
from typing import Any

from protocols.config_files import is_group

CHECKED_SECTIONS: tuple[str, ...] = ("eval", "protocol", "budget", "method.train", "dataset", "renderer")
"""Sections whose keys are checked by their type (tests/test_known_keys.py holds each to it)."""

HYDRA = "hydra"


def override_key(override: str) -> tuple[str, bool]:
    """The key an override sets and whether it adds it (``+key=``, ``++key=``); ``~key`` deletes."""
    text = override.split("=", 1)[0]
    adds = text.startswith("+")
    return text.lstrip("+~"), adds


def flat_keys(node: Any, prefix: str = "") -> dict[str, Any]:
    """Every dotted key of a plain nested mapping with its value (mappings included)."""
    out: dict[str, Any] = {}
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}.{k}" if prefix else str(k)
            out[key] = v
            out.update(flat_keys(v, key))
    return out


def _open(key: str, known: dict[str, Any]) -> bool:
    """Whether ``key`` lies below a mapping the config leaves open (an empty ``{}``)."""
    parts = key.split(".")
    return any(known.get(".".join(parts[:i])) == {} for i in range(1, len(parts)))


def _checked(key: str) -> bool:
    return any(key == s or key.startswith(s + ".") for s in CHECKED_SECTIONS)


def nearest(key: str, known: list[str]) -> str | None:
    """The known key closest to ``key``: a close spelling beside it (``grid.seed`` -> ``grid.seeds``),
    else one with the same last part (``steps`` -> ``protocol.steps``), else the closest spelling
    below the deepest section of ``key`` that exists (``executor.slurm.partiton``); None where
    nothing is close (a guess from another section would mislead)."""
    parent, _, leaf = key.rpartition(".")
    siblings = {k.rpartition(".")[2]: k for k in known if k.rpartition(".")[0] == parent}
    close = difflib.get_close_matches(leaf, list(siblings), n=1, cutoff=0.8)
    if close:
        return siblings[close[0]]
    same_leaf = [k for k in known if k.rpartition(".")[2] == leaf]
    if not same_leaf:   # a near spelling of a last part (``step`` -> ``protocol.steps``)
        close = difflib.get_close_matches(leaf, list({k.rpartition(".")[2] for k in known}), n=1, cutoff=0.85)
        same_leaf = [k for k in known if close and k.rpartition(".")[2] == close[0]]
    if same_leaf:
        return min(same_leaf, key=len)
    parts = key.split(".")
    for depth in range(len(parts) - 1, -1, -1):
        prefix = ".".join(parts[:depth])
        below = {k[len(prefix) + 1:] if prefix else k: k for k in known if not prefix or k.startswith(prefix + ".")}
        if below:
            close = difflib.get_close_matches(".".join(parts[depth:]), list(below), n=1, cutoff=0.6)
            return below[close[0]] if close else None
    return None


def unknown_key_message(override: str, known: list[str]) -> str:
    """``+steps=30: no setting is called steps, so nothing would read it; did you mean protocol.steps=30?``"""
    key, adds = override_key(override)
    value = override.split("=", 1)[1] if "=" in override else None
    near = nearest(key, known)
    section = next((s for s in CHECKED_SECTIONS if key.startswith(s + ".")), None)
    if near:
        hint = f"; did you mean {near}{'=' + value if value is not None else ''}?"
    elif section and not adds:
        hint = (f"; {section} takes keys the config does not show, added with +: +{override} ({section} "
                "checks them)")
    else:
        hint = ""
    return f"{override}: no setting is called {key}, so nothing would read it{hint} (settings: smgs run --help)"


def unread_keys(base: dict[str, Any], overrides: list[str]) -> list[str]:
    """A message for each key of ``overrides`` that nothing would read, given ``base``: the config
    composed from the same command line's group choices alone (``+experiment=``, ``dataset=``, ...).
    A key added (``+``) to a section that checks its own keys is left to that section."""
    flat = flat_keys(base)
    settings = [k for k, v in flat.items() if not isinstance(v, dict)]
    problems = []
    for o in overrides:
        key, adds = override_key(o)
        if is_group(key) or key.split(".")[0] == HYDRA or "@" in key or (adds and _checked(key)):
            continue
        if key not in flat and not _open(key, flat):
            problems.append(unknown_key_message(o, settings))
    return list(dict.fromkeys(problems))


def group_choices(overrides: list[str]) -> list[str]:
    """The overrides that pick config groups (what the known keys depend on)."""
    return [o for o in overrides if is_group(override_key(o)[0])]
