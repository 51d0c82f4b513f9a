"""`gt-bench`'s command line: one subcommand per benchmark, and the single command's old mode flags still work."""

from __future__ import annotations

import sys

import pytest
import typer.main
from typer.testing import CliRunner

from gaussiantalker.cli import bench as bench_cli
from tools.bench.app import app


def _options(command: str) -> set[str]:
    """The option names of one `gt-bench` subcommand."""
    group = typer.main.get_command(app)
    return {name for param in group.commands[command].params for name in param.opts if name.startswith("--")}


def test_help_lists_every_subcommand():
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in bench_cli.BENCH_COMMANDS:
        assert command in result.output, command
    assert set(typer.main.get_command(app).commands) == set(bench_cli.BENCH_COMMANDS)


@pytest.mark.parametrize("flag, command, kept", bench_cli.LEGACY_BENCH_MODES)
def test_each_old_mode_flag_maps_to_a_subcommand_that_takes_its_options(flag, command, kept):
    """What the rewrite keeps of an old invocation is exactly what the subcommand accepts (no option lost)."""
    assert set(kept) <= _options(command), set(kept) - _options(command)
    args, note = bench_cli.bench_args([flag, *(["/x"] if flag == "--baseline" else []), "--rounds", "2",
                                       "--torch-frames", "3"])
    assert args[0] == command and "--rounds" in args and "--torch-frames" not in args
    assert note.count("\n") == 0 and f"gt-bench {command}" in note and "--torch-frames" in note


def test_bare_options_run_frames():
    assert bench_cli.bench_args([]) == (["frames"], None)
    assert bench_cli.bench_args(["--sizes", "256", "--json=x.json"]) == (
        ["frames", "--sizes", "256", "--json=x.json"], None)
    assert set(bench_cli.FRAMES_OPTIONS) <= _options("frames")
    assert bench_cli.bench_args(["sweep", "--cases", "x"]) == (["sweep", "--cases", "x"], None)


def test_old_flag_form_still_works(monkeypatch, capsys):
    """`gt-bench --sweep --cases zoom` runs `gt-bench sweep --cases zoom` (which refuses the unknown case, before
    any speaker is built), with a one-line note on stderr."""
    monkeypatch.setattr(sys, "argv", ["gt-bench", "--sweep", "--cases", "zoom"])
    with pytest.raises(SystemExit) as exit_info:
        bench_cli.main()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[0] == "gt-bench: --sweep is now the subcommand `gt-bench sweep`; running that"
    assert "no sweep case matches 'zoom'" in err
