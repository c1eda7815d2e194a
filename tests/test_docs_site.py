"""The repository's conventions: the LICENSE pyproject states, a CITATION.cff that parses, and the
documentation site (mkdocs.yml over docs/) that builds in strict mode, every page in its nav."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tomllib
from pathlib import Path

import yaml  # PyYAML: mkdocs (in the dev extra) depends on it

REPO_ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
PAPER_TITLE = "Interaction-aware Decision Making with Adaptive Strategies under Merging Scenarios"


def test_license_is_the_one_pyproject_states() -> None:
    assert PYPROJECT["license"] == {"text": "MIT"}
    text = (REPO_ROOT / "LICENSE").read_text(encoding="utf-8")
    assert text.splitlines()[0] == "MIT License"
    assert "Copyright (c) 2026 the idas-sumo authors" in text
    assert 'THE SOFTWARE IS PROVIDED "AS IS", WITHOUT WARRANTY OF ANY KIND' in text


def test_citation_cites_this_tool_and_the_idas_paper() -> None:
    cff = yaml.safe_load((REPO_ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0"
    assert cff["type"] == "software"
    assert cff["version"] == PYPROJECT["version"]
    assert cff["license"] == PYPROJECT["license"]["text"]
    assert cff["title"].startswith(PYPROJECT["name"]) and cff["authors"] and cff["message"]
    (paper,) = cff["references"]
    assert paper["title"] == PAPER_TITLE and paper["year"] == 2019
    assert "IROS" in paper["conference"]["name"]
    assert [a["family-names"] for a in paper["authors"]] == ["Hu", "Nakhaei", "Tomizuka", "Fujimura"]
    # The README cites the same paper by the same title.
    assert f"*{PAPER_TITLE}*" in (REPO_ROOT / "README.md").read_text(encoding="utf-8")


def _nav_pages(nav: list) -> list[str]:
    pages: list[str] = []
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        pages += _nav_pages(value) if isinstance(value, list) else [value]
    return pages


def test_site_nav_holds_every_docs_page_and_the_index_keeps_the_readme_install() -> None:
    config = yaml.safe_load((REPO_ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    pages = _nav_pages(config["nav"])
    assert pages[0] == "index.md"
    assert sorted(pages) == sorted(p.name for p in (REPO_ROOT / "docs").glob("*.md"))
    readme = (REPO_ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    index = (REPO_ROOT / "docs" / "index.md").read_text(encoding="utf-8").splitlines()
    install = next(line for line in readme if line.startswith("python3.11 -m venv"))
    assert install in index


def test_site_builds_in_strict_mode(tmp_path: Path) -> None:
    # Strict: a link to a page or anchor that is not there fails the build (mkdocs.yml's validation).
    # Not --quiet: with it mkdocs 1.6.1 counts no warning, and strict passes a broken link.
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "index.html").is_file() and (tmp_path / "results" / "index.html").is_file()


def test_links_outside_docs_become_repository_paths_and_missing_ones_are_reported(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location("mkdocs_links", REPO_ROOT / "scripts" / "mkdocs_links.py")
    assert spec is not None and spec.loader is not None
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    docs = tmp_path / "docs"
    (docs / "img").mkdir(parents=True)
    (tmp_path / "experiments").mkdir()
    (tmp_path / "experiments" / "README.md").write_text("x")
    markdown = (
        "See [the variants](../experiments/README.md#retired), [`experiments/README.md`](../experiments/README.md),"
        " [nets](nets.md#x), [web](https://example.org) and [gone](../nope.md).\n"
        "```\n[kept](../experiments/README.md)\n```\n"
    )
    text, missing = hook.outside_links(markdown, docs, docs, tmp_path)
    assert text == (
        "See the variants (`experiments/README.md`), `experiments/README.md`,"
        " [nets](nets.md#x), [web](https://example.org) and [gone](../nope.md).\n"
        "```\n[kept](../experiments/README.md)\n```\n"
    )
    assert missing == ["../nope.md"]
