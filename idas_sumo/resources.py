"""Files shipped inside the package (the merge net, trained policies, scenario and config TOML) and how
a path the user types finds them.

They live in the package's own data folders (``idas_sumo/sumo_nets``, ``idas_sumo/policies``,
``idas_sumo/scenarios``) so that a wheel or a non-editable install carries them; users name them as
they appear in the docs, e.g. ``sumo_nets/tjunction.net.xml`` or ``scenarios/eval_paper.toml``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = [
    "DEFAULT_NET",
    "DEFAULT_NET_NAME",
    "DEFAULT_TRAIN_CONFIG",
    "DEFAULT_TRAIN_CONFIG_NAME",
    "POLICY_DIR",
    "SCENARIO_DIR",
    "resolve_user_path",
    "shipped",
]

# An unpacked install (wheel, editable, checkout) gives a real directory, which SUMO and torch need;
# str() rather than a cast so a zip import fails later with the ordinary "not found" line.
_PACKAGE_DIR = Path(str(files("idas_sumo")))

DEFAULT_NET_NAME = "sumo_nets/tjunction.net.xml"
"""The default net as users type it (``netgen --out`` writes here, relative to the current directory)."""
DEFAULT_TRAIN_CONFIG_NAME = "scenarios/train_default.toml"


def shipped(relative: str | Path) -> Path:
    """The shipped file or folder ``relative`` (e.g. ``"policies/idas.pt"``); it need not exist."""
    return _PACKAGE_DIR / relative


DEFAULT_NET = shipped(DEFAULT_NET_NAME)
DEFAULT_TRAIN_CONFIG = shipped(DEFAULT_TRAIN_CONFIG_NAME)
POLICY_DIR = shipped("policies")
SCENARIO_DIR = shipped("scenarios")


def resolve_user_path(text: str | Path) -> Path:
    """The path the user gave if it exists; else, if it is relative and names a shipped file, that file.

    So ``--net sumo_nets/tjunction.net.xml`` works from any directory, while a file of that name in the
    current directory still wins. Anything else comes back unchanged, so the caller's own "not found"
    error names what the user typed. Also the argparse ``type=`` of input-file flags (argparse applies it
    to a string default too).
    """
    path = Path(text)
    if path.exists() or path.is_absolute() or ".." in path.parts:
        return path
    candidate = shipped(path)
    return candidate if candidate.is_file() else path
