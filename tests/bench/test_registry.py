"""bench/registry.py: every benchmark declared once, the CLI's `bench` commands built from it, and
no benchmark module importing the CLI (which loads them all)."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import typer
from typer.testing import CliRunner

from bench.registry import BENCHMARKS
from fluidnexus.cli import app

BENCH = Path(__file__).resolve().parents[2] / "bench"
# bench/*.py with a `command` that are tools, not benchmarks: not sub-commands of `fluidnexus bench`.
TOOLS = {"reconstruct_plot": "plots `bench reconstruct --json` results; measures nothing"}


def _has_command(path: Path) -> bool:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return any(isinstance(node, ast.FunctionDef) and node.name == "command" for node in tree.body)


def test_the_registry_lists_every_benchmark_module() -> None:
    with_command = {path.stem for path in BENCH.glob("*.py") if _has_command(path)}
    assert with_command - set(TOOLS) == set(BENCHMARKS)
    assert set(TOOLS) <= with_command  # a tool that no longer exists leaves this list too
    assert all(description and "\n" not in description for description in BENCHMARKS.values())


def test_the_cli_bench_commands_are_the_registry() -> None:
    group = typer.main.get_command(app).commands["bench"]
    assert list(group.commands) == list(BENCHMARKS)
    for name, description in BENCHMARKS.items():
        assert group.commands[name].help == description
    listing = CliRunner().invoke(app, ["bench", "--help"], env={"COLUMNS": "400"})
    assert listing.exit_code == 0
    for description in BENCHMARKS.values():
        assert description in listing.output


def test_no_bench_module_imports_the_cli() -> None:
    """Directly (any import statement, inside functions too) or through what it imports."""
    for path in BENCH.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n == "fluidnexus.cli" or n.startswith("fluidnexus.cli.") for n in names), (path.name, names)
    modules = sorted(f"bench.{path.stem}" for path in BENCH.glob("*.py"))
    loaded = (f"import importlib, sys; [importlib.import_module(m) for m in {modules!r}]; "
              "print(sorted(m for m in sys.modules if m.startswith('fluidnexus.cli')))")
    done = subprocess.run([sys.executable, "-c", loaded], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]", done.stdout


def test_a_script_and_its_cli_command_refuse_bad_input_alike() -> None:
    """`python bench/NAME.py` runs through the registry too: same help line, same `error:` and exit 2."""
    script = subprocess.run([sys.executable, str(BENCH / "generative.py"), "--size", "huge"], capture_output=True, text=True)
    cli = CliRunner().invoke(app, ["bench", "generative", "--size", "huge"])
    assert script.returncode == cli.exit_code == 2
    assert script.stderr.startswith("error: --size") and script.stderr.strip() == cli.output.strip()
    helped = subprocess.run([sys.executable, str(BENCH / "generative.py"), "--help"], capture_output=True, text=True,
                            env={**os.environ, "COLUMNS": "400"})
    assert helped.returncode == 0 and BENCHMARKS["generative"] in helped.stdout
