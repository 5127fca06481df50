import json
import subprocess
import sys

import pytest

from vbrl_ros.cli import build_parser, main


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for command in ("train", "eval", "simulate", "replay", "bench", "demo"):
        assert command in out


@pytest.mark.parametrize("command", ["train", "eval", "simulate", "replay", "bench", "demo"])
def test_each_subcommand_documents_itself(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([command, "--help"])
    assert exit_info.value.code == 0
    assert "usage: vbrl " + command in capsys.readouterr().out


def test_user_errors_are_one_line_and_exit_2(tmp_path, capsys):
    code = main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "m.npz"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vbrl train: error:") and "\n" not in err


def test_console_script_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "vbrl_ros.cli", "--help"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "simulate" in result.stdout


def test_bench_prints_a_table_and_writes_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--repeats", "2", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "describe one scan" in table and "speed-up" in table
    figures = json.loads(out.read_text())
    assert figures["describe"]["points"] == 120_000
    assert figures["describe"]["median_ms"] > 0
    s = figures["solver_iteration"]
    assert s["fast_path"] == "woodbury" and s["speedup"] > 1  # n=700 < d: n x n beats d x d
