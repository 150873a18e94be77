"""The Hydra config tree (configs/) as files: where it is, which names each group offers, and what
each file says it is (its opening comment). Nothing here imports Hydra or torch, so the command
line's help and ``smgs list`` answer at once."""

from __future__ import annotations

import re
from pathlib import Path

CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")
ABOUT_CHARS = 160   # whole sentences of a config's opening comment, up to about this many characters
SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z\"'(<`])")


def has_config(group: str, name: str) -> bool:
    """Whether configs/<group>/<name>.yaml exists (a method, dataset or budget with a file of its own)."""
    return (Path(CONFIG_DIR) / group / f"{name}.yaml").exists()


def config_names(group: str) -> list[str]:
    """The names configs/<group>/ offers (its files), sorted."""
    return sorted(p.stem for p in (Path(CONFIG_DIR) / group).glob("*.yaml"))


def is_group(key: str) -> bool:
    """Whether an override's key selects a config group (``dataset=colmap``, ``+experiment=smoke``)
    rather than setting a value: a folder of configs/, or a group made in code (``method/train``)."""
    return "." not in key and ("/" in key or (Path(CONFIG_DIR) / key).is_dir())


def sentences(text: str) -> list[str]:
    """``text`` cut after each full stop that ends a sentence: followed by a capital, and outside
    brackets (not "supp. Sec. 6" inside "(paper Sec. 4.1, supp. Sec. 6)")."""
    out, start = [], 0
    for m in SENTENCE_END.finditer(text):
        head = text[start:m.start()]
        if head.count("(") == head.count(")") and head.count("[") == head.count("]"):
            out.append(head)
            start = m.end()
    return out + [text[start:]]


def first_comment(path: Path) -> str:
    """What a config file is: the whole sentences that fit in ``ABOUT_CHARS`` (at least one, never
    cut) of its opening comment block, without the ``@package`` directive."""
    block: list[str] = []
    for line in path.read_text().splitlines():
        text = line.lstrip("#").strip()
        if not line.startswith("#") or (block and not text):
            break
        if text and not text.startswith("@package"):
            block.append(text)
    about = ""
    for sentence in sentences(" ".join(block)):
        if about and len(about) + 1 + len(sentence) > ABOUT_CHARS:
            break
        about = f"{about} {sentence}".strip()
    return about


def config_entries(group: str) -> list[tuple[str, str]]:
    """Each file of configs/<group>/ with what its opening comment says it is."""
    return [(name, first_comment(Path(CONFIG_DIR) / group / f"{name}.yaml")) for name in config_names(group)]


def top_level_settings() -> list[tuple[str, str, str]]:
    """The top-level settings of configs/config.yaml as written there: (key, default, its comment,
    on its line or the line above), a section (``grid:``, ``eval:``) as ``key.*`` with its keys."""
    import yaml   # PyYAML, which Hydra depends on: a few milliseconds

    text = (Path(CONFIG_DIR) / "config.yaml").read_text()
    sections = {k: v for k, v in (yaml.safe_load(text) or {}).items() if isinstance(v, dict)}
    out: list[tuple[str, str, str]] = []
    above = ""
    for line in text.splitlines():
        m = re.match(r"([A-Za-z_]\w*):\s*([^#]*?)\s*(?:#\s*(.*))?$", line)
        if m and m.group(1) not in ("defaults", "hydra"):
            key, value, comment = m.groups()
            if key in sections:
                keys = ", ".join(sections[key])
                out.append((f"{key}.*", "", f"{comment or above}: {keys}" if comment or above else keys))
            else:
                out.append((key, value, comment or above))
        above = line.lstrip("#").strip() if line.startswith("#") else ""
    return out
