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
