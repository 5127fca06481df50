import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from vbrl_ros.tools.cli import build_parser, main


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


def _subcommand_parsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {"vbrl": parser, **subparsers.choices}


# reST a user should never read: ``literal``, :role:`target`, `link`_
MARKUP = re.compile(r"``|:[a-z]+:`|`[^`]+`_")


@pytest.mark.parametrize("command", list(_subcommand_parsers()))
def test_help_is_plain_text_and_every_argument_has_some(command):
    parser = _subcommand_parsers()[command]
    text = parser.format_help()
    assert not MARKUP.search(text), MARKUP.search(text).group(0)
    assert "(default: None)" not in text and "(default: False)" not in text
    for action in parser._actions:
        assert action.help, f"vbrl {command}: {action.option_strings or action.dest} has no help"


def test_user_errors_are_one_line_and_exit_2(tmp_path, capsys):
    code = main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "m.npz"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vbrl train: error:") and "\n" not in err


def test_console_script_entry_point_runs():
    result = subprocess.run([sys.executable, "-m", "vbrl_ros.tools.cli", "--help"],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "simulate" in result.stdout


def test_bench_prints_a_table_and_writes_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--repeats", "2", "--sizes", "200,500", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "describe one scan" in table and "speed-up" in table
    assert "query+insert" in table and "brute force" in table and "prune 0.0001" in table
    figures = json.loads(out.read_text())
    assert figures["describe"]["points"] == 120_000
    assert figures["describe"]["median_ms"] > 0
    assert figures["describe_polar"]["dimension"] > figures["describe"]["dimension"]
    assert figures["describe_polar"]["median_ms"] > 0
    s = figures["solver_iteration"]
    assert s["fast_path"] == "woodbury" and s["speedup"] > 1  # n=700 < d: n x n beats d x d
    index = figures["index"]
    assert index["sizes"] == [200, 500]
    for name, sectors in (("cartesian", 1), ("polar", 24)):
        shape = index["shapes"][name]
        assert shape["sectors"] == sectors and shape["params"]["sectors"] == sectors
        assert [row["n"] for row in shape["scale"]] == [200, 500]
        for row in shape["scale"]:
            assert row["brute_force_query_ms"] > 0
            cross = row["cross_season"]  # small databases: always within the time budget
            assert cross["queries"] >= 10
            assert 0 <= cross["top1_agreement"] <= 1 and 0 <= cross["recall_at_1_exact"] <= 1
            for storage in ("float32", "float16"):
                r = row[storage]
                assert r["query_insert_ms"] > 0 and r["p95_query_insert_ms"] >= r["query_insert_ms"]
                assert 0 <= r["recall_at_1_vs_exact"] <= 1 and r["recall_queries"] >= 5
                assert 0 <= r["yaw_correct"] <= 1
        m32, m16 = shape["memory"]["float32"], shape["memory"]["float16"]
        assert m32["descriptor"] == 2 * m16["descriptor"] == 4 * shape["d_active"]
        assert m32["total"] == (m32["descriptor"] + m32["key"] + m32["yaw_key"] + m32["metadata"] + m32["place"]
                                + m32["sees_all_round"])
        # a keyframe also described all round stores another descriptor with its keys and its row
        assert m32["all_round"] == m32["descriptor"] + m32["key"] + m32["yaw_key"] + 8
        assert (m32["yaw_key"] > 0) == (sectors > 1)
        drive = shape["drive"]
        assert 0 <= drive["recall_at_1_index"] <= 1 and 0 <= drive["top1_agreement"] <= 1
    pruning = index["pruning"]
    level = str(pruning["prune"])
    assert pruning["active_rows"][level] < pruning["active_rows"]["0"]
    assert (pruning["bytes_per_keyframe"][level]["float32"]
            < pruning["bytes_per_keyframe"]["0"]["float32"])
    assert 0 <= pruning["drive_vs_unpruned_exact"]["top1_agreement"] <= 1


def test_bench_polar_model_must_be_polar(capsys):
    from vbrl_ros.model.builtin import PAPER_MODEL_PATH

    assert main(["bench", "--sizes", "", "--polar-model", str(PAPER_MODEL_PATH)]) == 2
    assert "needs a polar model" in capsys.readouterr().err


def test_bench_sizes_are_checked(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "--sizes", "1000,abc"])
    assert "comma-separated integers" in capsys.readouterr().err


TERMINATED_SCRIPT = """
import argparse, itertools, sys, time
from vbrl_ros.features.parallel import bounded_map, worker_pool
from vbrl_ros.tools.cli import run_parsed

def endless_work(args):
    with worker_pool(2, time.time, ()) as pool:
        for k, _ in enumerate(bounded_map(pool, time.sleep, itertools.repeat(0.05), 8)):
            if k == 4:
                print("working", flush=True)
    return 0

if __name__ == "__main__":
    sys.exit(run_parsed(argparse.Namespace(func=endless_work, command="test")))
"""


def _descendants(pid: int) -> set[int]:
    """Every living process below ``pid`` (read from /proc)."""
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    parents[int(entry)] = int(stat.read().rsplit(")", 1)[1].split()[1])
            except OSError:  # ended meanwhile
                pass
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads the process tree from /proc")
def test_sigterm_shuts_a_commands_worker_processes_down(tmp_path):
    """Killed with SIGTERM mid-run, a command exits 143 after its worker pool has stopped its
    processes: none is left behind (before, the fork server and its workers kept running)."""
    script = tmp_path / "endless.py"
    script.write_text(TERMINATED_SCRIPT)
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        assert process.stdout.readline().strip() == "working"
        helpers = _descendants(process.pid)
        assert len(helpers) >= 3  # the fork server and two workers (and a resource tracker)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 143
        assert "terminated" in process.stderr.read()
    finally:
        process.kill()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and any(os.path.exists(f"/proc/{pid}") for pid in helpers):
        time.sleep(0.1)
    assert not [pid for pid in helpers if os.path.exists(f"/proc/{pid}")]
