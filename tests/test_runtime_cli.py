"""``resloc swarm`` and ``resloc robot`` on the command line: lazy imports, one-line errors
with exit code 2, and Ctrl-C stopping every process cleanly with atomic partial outputs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.experiments.config import default_scenario
from resloc.experiments.config_dump import dump_scenario
from resloc.runtime.swarm import stop_process

runner = CliRunner()


def test_help_does_not_import_zenoh() -> None:
    code = (
        "import sys; from resloc.cli.app import app; "
        "from typer.testing import CliRunner; r = CliRunner().invoke(app, ['--help']); "
        "assert r.exit_code == 0 and 'swarm' in r.output and 'robot' in r.output; "
        "print(sorted(m for m in sys.modules if m.startswith(('zenoh', 'msgpack'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def _one_line_error(result, *words: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), result.output
    for w in words:
        assert w in lines[0], lines[0]


def test_swarm_bad_input_is_one_line_exit_2(tmp_path) -> None:
    key = tmp_path / "k"
    res = runner.invoke(
        app,
        ["swarm", "--listen", "udp:bogus", "--key-file", str(key), "--out", str(tmp_path / "o")],
    )
    _one_line_error(res, "--listen", "tcp/127.0.0.1:7447")
    full = tmp_path / "full"
    full.mkdir()
    (full / "x").write_text("keep")
    res = runner.invoke(app, ["swarm", "--out", str(full), "--key-file", str(key)])
    _one_line_error(res, "--out", "--overwrite")
    assert (full / "x").read_text() == "keep"
    sc = tmp_path / "two.toml"
    sc.write_text(dump_scenario(default_scenario().replace(**{"run.trials": 2})))
    res = runner.invoke(
        app, ["swarm", str(sc), "--key-file", str(key), "--out", str(tmp_path / "o")]
    )
    _one_line_error(res, "run.trials")
    sc.write_text(dump_scenario(default_scenario().replace(**{"estimator.fusion": "tracked"})))
    res = runner.invoke(
        app, ["swarm", str(sc), "--key-file", str(key), "--out", str(tmp_path / "o")]
    )
    _one_line_error(res, "estimator.fusion")
    os.chmod(key, 0o644)
    res = runner.invoke(app, ["swarm", "--key-file", str(key), "--out", str(tmp_path / "o")])
    _one_line_error(res, "--key-file", "chmod 600")
    assert not (tmp_path / "o").exists()


def test_robot_bad_input_is_one_line_exit_2(tmp_path) -> None:
    sc = tmp_path / "sc.toml"
    sc.write_text(dump_scenario(default_scenario()))
    key = tmp_path / "k"
    base = ["robot", "--config", str(sc), "--key-file", str(key)]
    _one_line_error(runner.invoke(app, [*base, "--id", "0"]), "--connect")
    _one_line_error(
        runner.invoke(app, [*base, "--id", "99", "--connect", "tcp/127.0.0.1:9"]), "--id 99"
    )
    _one_line_error(
        runner.invoke(app, [*base, "--id", "0", "--connect", "tcp/127.0.0.1"]), "--connect"
    )
    res = runner.invoke(
        app,
        [
            "robot",
            "--id",
            "0",
            "--config",
            str(tmp_path / "no.toml"),
            "--connect",
            "tcp/127.0.0.1:9",
            "--key-file",
            str(key),
        ],
    )
    _one_line_error(res, "--config")
    # Nobody listens on port 9 of the loopback: the session cannot link.
    res = runner.invoke(
        app, [*base, "--id", "0", "--connect", "tcp/127.0.0.1:9", "--connect-timeout", "1"]
    )
    _one_line_error(res, "tcp/127.0.0.1:9")


def _children_of(tmp_path: Path) -> list[int]:
    """Pids of processes whose command line names a file under ``tmp_path`` (the swarm's
    options file lives in its work directory there)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(tmp_path) in cmd and "resloc.runtime.process" in cmd:
            pids.append(int(entry.name))
    return pids


def test_ctrl_c_stops_every_process_and_writes_partial_results(tmp_path) -> None:
    sc = tmp_path / "sc.toml"
    sc.write_text(
        dump_scenario(default_scenario().replace(**{"team.robots": 4, "run.steps": 100000}))
    )
    out = tmp_path / "out"
    env = dict(os.environ, TMPDIR=str(tmp_path))
    cmd = [
        sys.executable,
        "-c",
        "from resloc.cli.app import main; main()",
        "swarm",
        str(sc),
        "--out",
        str(out),
        "--key-file",
        str(tmp_path / "k"),
        "--no-progress",
        "--no-plots",
        "--robots-per-process",
        "2",
        "--filter",
        "ekf",
    ]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 90
        while not (out / "runtime.json").exists() and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.2)
        assert (out / "runtime.json").exists(), "no snapshot within 90 s"
        children = _children_of(tmp_path)
        assert len(children) == 5  # world, radio, recorder, 2 robot processes
        t0 = time.monotonic()
        os.kill(proc.pid, signal.SIGINT)
        code = proc.wait(timeout=60)
        assert time.monotonic() - t0 < 30
    finally:
        stop_process(proc, 5.0)
        left = _children_of(tmp_path)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    assert code == 130, proc.stderr.read().decode()
    assert left == [], f"orphans: {left}"
    runtime = json.loads((out / "runtime.json").read_text())
    assert runtime["end"].startswith("interrupted") and runtime["partial"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == runtime["steps_completed"] > 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


def test_two_hosts_through_an_external_router(tmp_path) -> None:
    """The README's zenohd set-up on the loopback: a router of its own (a Zenoh session in
    router mode stands in for zenohd), the swarm without a router (``--connect``) and robot 4
    started separately with ``resloc robot`` (``--external-robots 4``)."""
    from resloc.runtime.transport import free_endpoint, open_session

    endpoint = free_endpoint()
    router = open_session("router", [endpoint], [])
    sc = tmp_path / "sc.toml"
    sc.write_text(dump_scenario(default_scenario().replace(**{"team.robots": 5, "run.steps": 40})))
    key = tmp_path / "k"
    robot = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from resloc.cli.app import main; main()",
            "robot",
            "--id",
            "4",
            "--config",
            str(sc),
            "--connect",
            endpoint,
            "--key-file",
            str(key),
            "--filter",
            "ekf",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        res = runner.invoke(
            app,
            [
                "swarm",
                str(sc),
                "--connect",
                endpoint,
                "--external-robots",
                "4",
                "--key-file",
                str(key),
                "--out",
                str(tmp_path / "out"),
                "--no-plots",
                "--filter",
                "ekf",
            ],
        )
        code = robot.wait(timeout=30)
    finally:
        stop_process(robot, 5.0)
        router.close()
    assert res.exit_code == 0, res.output
    assert code == 0, robot.stdout.read().decode()
    runtime = json.loads((tmp_path / "out" / "runtime.json").read_text())
    assert runtime["end"] == "complete" and runtime["steps_completed"] == 40
    est = dict(np.load(tmp_path / "out" / "estimates.npz"))
    assert est["fed"][1:, 4].all()  # the external robot took part in every step
    assert "estimate" in res.output and "MSLE" in res.output
