"""The command line: every subcommand's --help works and explains itself; errors are clear."""

from __future__ import annotations

import subprocess
import sys

import pytest

import argparse

from sfmloc.cli.main import COMMANDS, build_parser, main


def command_names() -> list[str]:
    """The subcommands as the parser registers them (module names may differ: bench_transport)."""
    for action in build_parser()._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []


def test_every_command_module_registers_a_command():
    assert len(command_names()) >= len(COMMANDS)


def test_top_level_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for name in command_names():
        assert name in out


@pytest.mark.parametrize("command", command_names())
def test_each_command_help(command, capsys):
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: sfmloc " + command)
    assert len(out) > 200  # explains its options


def test_console_script_runs():
    r = run_cli("--version")
    assert r.returncode == 0 and r.stdout.startswith("sfmloc ")


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "sfmloc", *args], capture_output=True, text=True)


def test_errors_exit_non_zero_with_a_message(tmp_path):
    r = run_cli("map", "verify", str(tmp_path / "missing"))
    assert r.returncode == 1 and "CORRUPT" in r.stdout and "not a folder" in r.stdout
    r = run_cli("build", "x", "--out", str(tmp_path), "--images", str(tmp_path / "none"))
    assert r.returncode == 2 and "does not exist" in r.stderr and "Traceback" not in r.stderr
    r = run_cli("build", "bad/name", "--out", str(tmp_path), "--images", str(tmp_path))
    assert r.returncode == 2 and "invalid map name" in r.stderr


def test_parser_builds():
    assert build_parser().prog == "sfmloc"
