"""The repository around the code: formatting and lint, the docs build, the docs in step with the
command line and the configs, and no development history in tracked files."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from unittest import mock

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(*command: str) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True)


def test_ruff_lint_and_format():
    ruff = [sys.executable, "-m", "ruff"]
    lint, form = run(*ruff, "check", "."), run(*ruff, "format", "--check", ".")
    assert lint.returncode == 0, lint.stdout + lint.stderr
    assert form.returncode == 0, form.stdout + form.stderr


def test_the_package_type_checks():
    """mypy over src/ (its settings in pyproject.toml): the Agent protocol, configs and policies
    as typed, every call as its signature allows."""
    result = run(sys.executable, "-m", "mypy")
    assert result.returncode == 0, result.stdout + result.stderr


# The package's layers, lowest first: a module imports only from its own layer and those below
# (the package itself, dva/__init__.py, is the public surface on top).
LAYERS = ("errors", "tasks", "envs", "networks", "configs", "algorithms", "runner", "analysis", "cli", "")


def package_imports() -> dict[str, set[str]]:
    """Every module of src/dva and the dva modules it imports, function-level imports included
    (``from dva.x import y`` counts as dva.x.y where that is a module)."""
    import ast

    source = ROOT / "src"
    files = {
        ".".join(path.relative_to(source).with_suffix("").parts).removesuffix(".__init__"): path
        for path in (source / "dva").rglob("*.py")
    }
    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        imported: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported |= {
                    f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in files else node.module
                    for alias in node.names
                }
        graph[module] = {name for name in imported if name in files and name != module}
    return graph


def layer(module: str) -> int:
    return LAYERS.index(module.removeprefix("dva").lstrip(".").split(".")[0])


def test_no_module_imports_a_layer_above_it_and_no_import_cycle():
    """errors → tasks → envs → networks → configs → algorithms → runner → analysis → cli: an
    import that climbs (even inside a function) would tangle the layers, and a cycle would make
    the import order matter."""
    graph = package_imports()
    assert len(graph) > 40
    upward = [
        f"{module} imports {name}" for module, names in graph.items() for name in names if layer(name) > layer(module)
    ]
    assert not upward, upward
    seen: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> None:
        seen[module] = 1
        for name in sorted(graph[module]):
            assert seen.get(name) != 1, f"import cycle: {' → '.join([*path, module, name])}"
            if name not in seen:
                visit(name, [*path, module])
        seen[module] = 2

    for module in sorted(graph):
        if module not in seen:
            visit(module, [])


def test_only_the_environment_factory_asks_whether_a_task_is_dm_controls():
    """dm_control's tasks differ from this project's in one place: dva.envs.factory (with
    dva.envs.dmc, which defines them)."""
    asking = [
        path.relative_to(ROOT).as_posix()
        for path in (ROOT / "src" / "dva").rglob("*.py")
        if "is_dmc(" in path.read_text()
    ]
    assert sorted(asking) == ["src/dva/envs/dmc.py", "src/dva/envs/factory.py"]


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


FLAG = r"--[a-z][a-z0-9-]*(?:\.[a-z0-9-]+|\.\*)?"


def cli_commands() -> list[list[str]]:
    from dva import cli

    return [[name] for name in cli.COMMANDS if name != "analyze"] + [["analyze", name] for name in cli.ANALYSES]


def help_flags(command: list[str]) -> set[str]:
    """The options ``dva COMMAND --help`` lists (each at the start of its entry, not those its
    descriptions mention)."""
    from dva import cli

    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit), mock.patch.dict(os.environ, {"COLUMNS": "80"}):
        cli.main([*command, "--help"])
    # One column at 80 characters: an entry's line (its flags and their types) starts two spaces
    # in, its description six further.
    entries = re.findall(r"^[│ ] (--.*)$", out.getvalue(), re.M)
    assert out.getvalue().startswith("usage: dva"), command
    return {flag for entry in entries for flag in re.findall(FLAG, entry)} - {"--help"}


def page_sections(page: str) -> dict[str, str]:
    """The text docs/cli.md gives each command: its ``## `dva NAME`` section, or for an analysis its
    table row."""
    sections = {}
    for block in re.split(r"\n## ", page)[1:]:
        name = re.match(r"`dva ([a-z]+)", block)
        if name and name[1] != "analyze":
            sections[name[1]] = block
    for row in re.findall(r"^\| `dva analyze ([a-z]+)` \|(.*)$", page, re.M):
        sections[f"analyze {row[0]}"] = row[1]
    return sections


def docs_against_help(sections: dict[str, str], helps: dict[str, set[str]]) -> list[str]:
    """Both directions: each option a command's help lists that its docs lack ("undocumented"),
    and each option its docs give that its help lacks ("phantom"); `--shac.*` stands for its group."""
    problems = []
    for command, flags in helps.items():
        text = sections.get(command)
        if text is None:
            problems.append(f"dva {command}: no section")
            continue
        documented = set(re.findall(FLAG, text))
        groups = {flag.split(".")[0] + ".*" for flag in flags if "." in flag}
        for flag in sorted(flags):
            if flag not in documented and flag.split(".")[0] + ".*" not in documented:
                problems.append(f"dva {command} {flag}: undocumented")
        for flag in sorted(documented - flags - groups):
            problems.append(f"dva {command} {flag}: phantom (not in its --help)")
    return problems


def test_cli_page_and_help_agree_both_ways():
    page = (ROOT / "docs" / "cli.md").read_text()
    helps = {" ".join(command): help_flags(command) for command in cli_commands()}
    problems = docs_against_help(page_sections(page), helps)
    assert not problems, "docs/cli.md and the parsers disagree: " + "; ".join(problems)


def test_the_docs_check_catches_a_phantom_and_a_missing_option():
    sections = {"train": "| `--task` | … |\n| `--shac.*` | … |\n| `--colour` | a phantom |"}
    helps = {"train": {"--task", "--shac.horizon", "--seed"}}
    assert docs_against_help(sections, helps) == [
        "dva train --seed: undocumented",
        "dva train --colour: phantom (not in its --help)",
    ]


def test_algorithm_and_task_lists_match_the_registries():
    from dva.algorithms import ALGORITHMS
    from dva.tasks import BUILTIN_TASKS, TARGET_RETURNS

    readme, cli_page = (ROOT / "README.md").read_text(), (ROOT / "docs" / "cli.md").read_text()
    listed = {
        "README": re.search(r"Algorithms \(`--algo`\):(.*?)\. Presets", readme, re.S)[1],
        "docs/cli.md": re.search(r"^\| `--algo` \|(.*)$", cli_page, re.M)[1],
    }
    for where, text in listed.items():
        assert set(re.findall(r"`([a-z0-9-]+)`", text)) == set(ALGORITHMS), where
    tasks_page = (ROOT / "docs" / "tasks.md").read_text()
    rows = set(re.findall(r"^\| `([a-z_]+)` \|", tasks_page, re.M))
    assert rows == set(BUILTIN_TASKS), f"docs/tasks.md's table lists {sorted(rows)}"
    # state obs | actions | episode | substeps | target return
    cells = re.findall(r"^\| `([a-z_]+)` \| \d+ \| \d+ \| \d+ \| \d+ \| (\d+) \|", tasks_page, re.M)
    assert {name: float(target) for name, target in cells} == TARGET_RETURNS, "docs/tasks.md's target returns"


def test_docs_state_the_python_and_package_versions():
    """The results page names the versions its numbers were measured with; each must be one that
    pyproject.toml's ranges allow, so a fresh install (which takes the newest release in range)
    runs the code those numbers came from. A range moved past them needs the results re-measured."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.specifiers import SpecifierSet

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    listed = project["dependencies"] + [r for extra in project["optional-dependencies"].values() for r in extra]
    allowed: dict[str, SpecifierSet] = {}
    for req in map(Requirement, listed):  # a package listed twice (main and an extra) must meet both
        allowed[req.name] = allowed.get(req.name, SpecifierSet()) & req.specifier
    index, results = (ROOT / "docs" / "index.md").read_text(), (ROOT / "docs" / "results.md").read_text()
    assert f"Python ≥ {project['requires-python'].removeprefix('>=')}" in index
    for package, name in (
        ("mujoco", "MuJoCo"),
        ("mujoco-mjx", "MJX"),
        ("jax", "JAX"),
        ("mujoco-warp", "mujoco-warp"),
        ("warp-lang", "warp-lang"),
    ):
        version = re.search(rf"{name} (\d[\w.]*\d)", results)
        assert version, f"docs/results.md does not state the {name} version"
        assert allowed[package].contains(version[1]), f"{name} {version[1]} is outside pyproject's {allowed[package]}"


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
