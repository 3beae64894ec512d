"""CI must run exactly what README.md tells a user to paste, so a green CI means the documented command works."""

from __future__ import annotations

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MARKER = "# README quick-start test command"


def readme_test_command(text: str) -> str:
    """The single command line of the fenced shell block under '## Quick start' that runs the tests."""
    section = re.search(r"^## Quick start\s*$(.*?)(?=^## |\Z)", text, re.MULTILINE | re.DOTALL)
    assert section, "README.md has no '## Quick start' section"
    blocks = re.findall(r"^```(?:bash|sh|shell|console)?\s*\n(.*?)^```", section.group(1), re.MULTILINE | re.DOTALL)
    test_blocks = [b for b in blocks if "pytest" in b]
    assert len(test_blocks) == 1, f"the Quick start section needs exactly one test command block, found {blocks}"
    lines = [line.strip() for line in test_blocks[0].splitlines() if line.strip()]
    assert len(lines) == 1, f"the quick-start test block must be one pasteable line, found {lines}"
    return lines[0].removeprefix("$ ")


def ci_test_command(text: str) -> str:
    """The line that follows the marker comment in .ci/run."""
    lines = text.splitlines()
    marks = [i for i, line in enumerate(lines) if line.startswith(MARKER)]
    assert len(marks) == 1, f".ci/run must contain the marker comment exactly once, found {len(marks)}"
    assert marks[0] + 1 < len(lines), ".ci/run ends at the marker comment"
    return lines[marks[0] + 1].strip()


def test_ci_runs_the_readme_test_command_verbatim() -> None:
    readme = readme_test_command((ROOT / "README.md").read_text())
    ci = ci_test_command((ROOT / ".ci" / "run").read_text())
    assert ci == readme


def test_readme_command_installs_lints_and_tests() -> None:
    command = readme_test_command((ROOT / "README.md").read_text())
    for part in ("python3 -m venv .venv", "pip install -e '.[test]'", "ruff check .", "python -m pytest -q"):
        assert part in command, part


def test_ci_script_is_an_executable_bash_script_that_stops_on_errors() -> None:
    path = ROOT / ".ci" / "run"
    text = path.read_text()
    assert text.startswith("#!/usr/bin/env bash\n")
    assert "set -euo pipefail" in text
    assert os.access(path, os.X_OK), ".ci/run is not executable"


def test_parsers_reject_drift() -> None:
    readme = (
        "# x\n\n## Quick start\n\n```bash\nposemetry serve\n```\n\n```bash\npython -m pytest -q\n```\n\n"
        "## Other\n\n```bash\npytest not this\n```\n"
    )
    assert readme_test_command(readme) == "python -m pytest -q"
    ci = f"#!/usr/bin/env bash\n{MARKER}:\nmake check\n"
    assert ci_test_command(ci) != readme_test_command(readme)
