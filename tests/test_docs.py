"""The project's docs carry what its code cites: nothing tracked points at files outside the repository."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
# A design document and a paper checkout that live beside the repository, not in it.
OUTSIDE_REFERENCE = re.compile(r"DESIGN\.md|\.\./shared/")


def test_no_tracked_file_cites_a_document_outside_the_repository() -> None:
    files = subprocess.run(
        ["git", "ls-files"], cwd=REPO_ROOT, check=True, capture_output=True, text=True
    ).stdout.split()
    texts = [
        f for f in files if f.endswith((".py", ".md", ".toml", ".json", ".sh")) and f != "tests/test_docs.py"
    ]
    offenders = [
        f"{name}:{n}"
        for name in texts
        for n, line in enumerate((REPO_ROOT / name).read_text(encoding="utf-8").splitlines(), 1)
        if OUTSIDE_REFERENCE.search(line)
    ]
    assert offenders == []


def test_design_notes_hold_the_sections_the_code_cites() -> None:
    notes = (REPO_ROOT / "docs" / "design-notes.md").read_text(encoding="utf-8")
    for section in ("### Definitions", "### Command line and exit codes", "### Evaluation output"):
        assert section in notes


README = REPO_ROOT / "README.md"
EXPERIMENTS = REPO_ROOT / "experiments"
INSTALL_AND_EVALUATE = (
    'python3.11 -m venv .venv && . .venv/bin/activate && pip install -e ".[dev]" && '
    "idas-sumo evaluate --baseline idas --scenarios 100 --out results/idas"
)
RUN_TESTS = ". .venv/bin/activate && python -m pytest -q"


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def test_readme_says_what_the_tool_is_first_and_stays_short() -> None:
    lines = _lines(README)
    assert lines[0] == "# idas-sumo"
    assert len(lines) <= 250
    definitions = [line for line in lines[:5] if line.startswith("idas-sumo is ") and "IDAS" in line]
    assert len(definitions) == 1
    assert definitions[0].count(". ") == 0  # one sentence


def test_readme_gives_the_two_commands_exactly_and_links_the_docs() -> None:
    lines = _lines(README)
    assert INSTALL_AND_EVALUATE in lines and RUN_TESTS in lines
    text = "\n".join(lines)
    for doc in ("docs/results.md", "docs/performance.md", "docs/distributed.md"):
        assert f"({doc})" in text and (REPO_ROOT / doc).is_file(), doc
    status = text.split("## Status", 1)[1].split("\n## ", 1)[0]
    assert sum(line.startswith("- ") for line in status.splitlines()) <= 6


def test_results_page_keeps_only_the_current_tables() -> None:
    assert len(_lines(REPO_ROOT / "docs" / "results.md")) <= 400


def test_experiments_readme_names_every_recipe_policy_and_retired_switch() -> None:
    text = (EXPERIMENTS / "README.md").read_text(encoding="utf-8")
    recipes = sorted(p.name for p in (EXPERIMENTS / "recipes").glob("*.toml"))
    policies = sorted({p.stem for p in (EXPERIMENTS / "policies").iterdir()})
    assert recipes and policies
    assert [r for r in recipes if f"`{r}`" not in text] == []
    assert [p for p in policies if f"`{p}`" not in text] == []
    retired = (
        "impede_blame",
        "brake_count",
        "collide_scale",
        "forfeit_finish",
        "cooperative_waits",
        "at_rest",
        "central_head",
        "central_input",
        "coma_actions",
        "coma_action_means",
        "central_action_rows",
        "critic_exploration",
        "IDAS_SUMO_OVERLAP_UPDATE",
        "ActionOverride",
    )
    assert [name for name in retired if name not in text] == []
    assert "git checkout 6499494" in text
