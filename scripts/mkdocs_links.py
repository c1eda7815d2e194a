"""MkDocs hook (mkdocs.yml ``hooks:``): a docs page's link to a file of the repository outside ``docs/``
(``../experiments/README.md``, ``../examples/sb3_maskable_ppo.py``) works on GitHub but is no page of the
site, so strict mode would fail on it. Here it becomes the file's repository path in code (``[the
variants](../experiments/README.md)`` -> ``the variants (`experiments/README.md`)``), and a link to a file
that is not in the repository is still a warning, so ``mkdocs build --strict`` fails on it."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

LINK = re.compile(r"(?<!!)\[(?P<text>[^\]\n]+)\]\((?P<target>[^)\s#]+)(?P<anchor>#[^)\s]*)?\)")
"""A markdown link (not an image) with a relative-looking target."""
FENCE = re.compile(r"^(```|~~~)", re.MULTILINE)
log = logging.getLogger("mkdocs.hooks.outside_links")


def outside_links(markdown: str, page_dir: Path, docs_dir: Path, repo_root: Path) -> tuple[str, list[str]]:
    """``markdown`` with its links to repository files outside ``docs_dir`` written as their paths; and
    the targets of such links that name no file or folder of the repository. Code blocks are left alone."""
    missing: list[str] = []

    def rewrite(match: re.Match[str]) -> str:
        target = match["target"]
        if "://" in target or target.startswith(("/", "mailto:")):
            return match[0]
        resolved = (page_dir / target).resolve()
        if resolved == docs_dir or docs_dir in resolved.parents:
            return match[0]  # a page of the site: MkDocs checks it
        if repo_root not in resolved.parents or not resolved.exists():
            missing.append(target)
            return match[0]
        path = resolved.relative_to(repo_root).as_posix()
        text = match["text"]
        return text if path in text else f"{text} (`{path}`)"

    parts = FENCE.split(markdown)
    # split keeps each fence marker: text, marker, code, marker, text, ...; rewrite only outside code.
    out, inside = [], False
    for i, part in enumerate(parts):
        if i % 2 == 1:  # a fence marker
            inside = not inside
            out.append(part)
        else:
            out.append(part if inside else LINK.sub(rewrite, part))
    return "".join(out), missing


def on_page_markdown(markdown: str, *, page: Any, config: Any, files: Any) -> str:
    docs_dir = Path(config["docs_dir"]).resolve()
    page_dir = (docs_dir / page.file.src_path).parent
    text, missing = outside_links(
        markdown, page_dir, docs_dir, Path(config["config_file_path"]).resolve().parent
    )
    for target in missing:
        log.warning("Doc file '%s' links to '%s', which is not in the repository", page.file.src_path, target)
    return text
