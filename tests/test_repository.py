"""The repository around the code: formatting and lint, the docs build, the docs in step with the
command line and the configs, and no development history in tracked files."""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(*command: str) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True)


def test_ruff_lint_and_format():
    ruff = [sys.executable, "-m", "ruff"]
    lint, form = run(*ruff, "check", "."), run(*ruff, "format", "--check", ".")
    assert lint.returncode == 0, lint.stdout + lint.stderr
    assert form.returncode == 0, form.stdout + form.stderr


def test_the_algorithms_never_import_the_training_loop():
    """The loop builds agents and loads a teacher above itself; an algorithm that imported the loop
    (even inside a function) would make the import circle algorithms → training → algorithms."""
    import ast

    for module in (ROOT / "src" / "dva" / "algorithms").glob("*.py"):
        for node in ast.walk(ast.parse(module.read_text())):
            names = [node.module] if isinstance(node, ast.ImportFrom) else []
            names += [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            assert not any(name and name.startswith("dva.training") for name in names), module.name


def test_docs_build_strictly(tmp_path):
    mkdocs = shutil.which("mkdocs", path=str(Path(sys.executable).parent))
    result = run(mkdocs, "build", "--strict", "--quiet", "--site-dir", str(tmp_path / "site"))
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "site" / "results" / "index.html").exists()


def test_no_development_history_in_tracked_files():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    # The brackets keep this line from matching itself.
    pattern = r"sessio[n] [0-9]|issu[e] [0-9]|spe[c] §|_s[0-9]{2}[._/]"
    result = run("git", "grep", "-n", "-I", "-i", "-E", pattern, "--", ".")
    assert result.stdout == "", result.stdout


def test_cli_page_lists_every_option():
    from dva import cli

    page = (ROOT / "docs" / "cli.md").read_text()
    commands = [["train"], ["eval"], ["plot"], ["compare"], ["sweep"], *[["analyze", name] for name in cli.ANALYSES]]
    missing = []
    for command in commands:
        help_text = subprocess.run(
            [sys.executable, "-m", "dva.cli", *command, "--help"],
            capture_output=True,
            text=True,
            env={**os.environ, "COLUMNS": "200"},
        ).stdout
        for flag in set(re.findall(r"--[a-z][a-z0-9-]*(?:\.[a-z0-9-]+)?", help_text)) - {"--help"}:
            group = flag.split(".")[0] + ".*"  # --shac.horizon is documented as the --shac.* group
            if f"`{flag}`" not in page and f"`{group}`" not in page and f"{flag} " not in page:
                missing.append(f"{' '.join(command)} {flag}")
    assert not missing, f"docs/cli.md lacks: {', '.join(sorted(missing))}"


def test_algorithms_page_lists_every_hyperparameter():
    from dva.algorithms import ALGORITHMS

    page = (ROOT / "docs" / "algorithms.md").read_text()
    missing = [
        f"{entry.config_type.__name__}.{field.name}"
        for entry in ALGORITHMS.values()
        for field in dataclasses.fields(entry.config_type)
        if f"`{field.name.replace('_', '-')}`" not in page
    ]
    assert not missing, f"docs/algorithms.md lacks: {', '.join(sorted(set(missing)))}"
