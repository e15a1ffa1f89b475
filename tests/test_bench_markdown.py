"""``skinstretch bench --markdown``: every table of the run, with its notes, the date, the machine and the command."""

import os
import types

import pytest

import skinstretch.experiments.commands.bench as bench_command
from skinstretch.cli import main
from skinstretch.experiments.bench import BenchTable


def _section(name, tables=None, error=None):
    def run(options):
        if error is not None:
            raise error
        assert options.quick
        return tables

    return types.SimpleNamespace(SECTION=name, DESCRIPTION=f"{name} things", run=run)


@pytest.fixture
def sections(monkeypatch):
    table = BenchTable("Speed | error", ["scene", "frames/s", "RMSE px", "met"],
                       [["flatL", 312.46, 0.03812, True], ["ridgeL", float("nan"), 0.041, False]],
                       notes=["RMSE against the simulator's truth"])
    fake = {"good": _section("good", [table]), "broken": _section("broken", error=RuntimeError("no camera"))}
    monkeypatch.setattr(bench_command, "available_sections", lambda: fake)
    return fake


def test_a_table_in_markdown_keeps_its_title_numbers_and_notes():
    table = BenchTable("T", ["a|b", "x"], [[1, 0.000123], [2, float("nan")]], notes=["n1", "n2"])
    lines = table.markdown().splitlines()
    assert lines[:4] == ["**T**", "", "| a\\|b | x |", "|---|---|"]
    assert lines[4:6] == ["| 1 | 1.23e-04 |", "| 2 | n/a |"]
    assert lines[-2:] == ["- n1", "- n2"]


def test_markdown_file_says_when_where_and_how(sections, tmp_path, capsys):
    out = tmp_path / "docs" / "benchmarks.md"
    assert main(["bench", "--only", "good", "--quick", "--workdir", str(tmp_path / "w"), "--markdown", str(out)]) == 0
    text = out.read_text()
    assert f"Written by `skinstretch bench --only good --quick --markdown {out}` on " in text
    assert f"Machine: {os.cpu_count()} cores, " in text and "CPython" in text
    assert "quick run" in text
    assert "## good: good things" in text and "**Speed | error**" in text
    assert "| flatL | 312.5 | 0.0381 | yes |" in text and "| ridgeL | n/a | 0.041 | no |" in text
    assert "- RMSE against the simulator's truth" in text
    # the plain tables still go to standard output; progress lines do not
    stdout = capsys.readouterr().out
    assert "Speed | error" in stdout and "running bench section" not in stdout


def test_a_failed_section_is_reported_and_the_others_still_run(sections, tmp_path, capsys):
    code = main(["bench", "--only", "broken,good", "--quick", "--workdir", str(tmp_path), "--markdown", "-"])
    captured = capsys.readouterr()
    assert code == 1
    assert "The section failed: RuntimeError: no camera" in captured.out and "| flatL |" in captured.out
    assert "section broken failed" in captured.err


def test_unknown_sections_are_named(sections, tmp_path, capsys):
    assert main(["bench", "--only", "nosuch", "--workdir", str(tmp_path)]) == 2
    assert "nosuch" in capsys.readouterr().err


def test_the_bench_says_a_repeated_log_message_once(monkeypatch, capsys):
    """Each of a section's clips would log the same line (a print's dpi, a short clip's note): the first one shows."""
    import logging

    def chatty(options):
        for name in ("p1", "p1", "p2", "p1"):
            logging.getLogger("skinstretch.simulators.x").info("%s: 500 dpi", name)
        return []

    monkeypatch.setattr(bench_command, "available_sections",
                        lambda: {"chatty": types.SimpleNamespace(SECTION="chatty", DESCRIPTION="d", run=chatty)})
    assert main(["bench", "--only", "chatty", "--quick"]) == 0
    err = capsys.readouterr().err
    assert err.count("p1: 500 dpi") == 1 and err.count("p2: 500 dpi") == 1
