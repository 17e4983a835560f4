"""The supervisor of ``resloc swarm``: hub, child processes, progress, clean shutdown.

:func:`run_swarm` opens the run's Zenoh router (a session in ``router`` mode on the
``listen`` endpoints; or none when every process connects to an external ``zenohd``), starts
the world, the radio, the recorder and one process per K robots as separate OS processes
(each in its own session and process group, so a terminal's Ctrl-C reaches only the
supervisor), follows the world's progress, and ends the run:

* normally: the world publishes ``end``, the recorder writes the outputs, everyone exits;
* Ctrl-C: the supervisor asks the world to stop; the recorder writes the steps so far;
* a lost world or recorder: the run ends with a message naming it; partial results are
  written (by the recorder, or its last snapshot);
* a lost robot: the others go on (it can re-join with ``resloc robot``).

Every child is waited for with a deadline, then terminated, then killed, by its pid.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from resloc.errors import ResLocError
from resloc.runtime.messages import SUPERVISOR, Codec, Kind, Verifier, load_or_create_key
from resloc.runtime.options import SwarmOptions
from resloc.runtime.transport import Bus, check_endpoint, free_endpoint, open_session

__all__ = ["SwarmError", "SwarmResult", "run_swarm", "spawn", "stop_process"]


class SwarmError(ResLocError):
    """The run could not complete (a process was lost); partial results may exist."""


@dataclass
class SwarmResult:
    """How a swarm run ended and what it wrote."""

    out: Path
    end: str
    runtime: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    interrupted: bool = False
    exit_codes: dict = field(default_factory=dict)
    logs: Path | None = None


def spawn(role: str, options_path: Path, ids: str | None, log: Path) -> subprocess.Popen:
    """Start one runtime process in its own session (own process group)."""
    cmd = [sys.executable, "-m", "resloc.runtime.process", role, str(options_path)]
    if ids is not None:
        cmd.append(ids)
    fh = log.open("wb")
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("MKL_NUM_THREADS", "1")
    return subprocess.Popen(
        cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True, env=env
    )


def stop_process(proc: subprocess.Popen, timeout_s: float = 5.0) -> int:
    """Wait for ``proc``; then SIGTERM it; then SIGKILL it (by pid). Returns its code."""
    for sig in (None, signal.SIGTERM, signal.SIGKILL):
        if sig is not None and proc.poll() is None:
            try:
                os.kill(proc.pid, sig)
            except ProcessLookupError:
                pass
        try:
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


def _tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(text[-lines:])


def run_swarm(
    options: SwarmOptions,
    listen: list[str],
    robots_per_process: int = 1,
    progress: Callable[[int, int], None] | None = None,
    log_dir: Path | None = None,
    watch: Callable[[int, dict[str, subprocess.Popen]], None] | None = None,
    external: tuple[int, ...] = (),
) -> SwarmResult:
    """Run one swarm to its end.

    Parameters
    ----------
    options : SwarmOptions
        ``scenario`` (a resolved TOML path) or ``replay``, ``out``, ``key_file``, ``connect``
        (external router endpoints, or empty to use the hub), ...
    listen : list of str
        Endpoints of the hub router (empty and no ``connect``: a free port on 127.0.0.1).
    robots_per_process : int
    progress : callable(k, steps), optional
    log_dir : Path, optional
        Where the children's logs go (default: a temporary directory, kept on failure).
    watch : callable(k, processes), optional
        Called with every progress step and the child processes by name (fault drills).
    external : tuple of int
        Robots this supervisor does not start: they run elsewhere (``resloc robot`` on
        another host) and the world waits for them at start-up.

    Returns
    -------
    SwarmResult

    Raises
    ------
    SwarmError
        The world or the recorder was lost (partial results in ``options.out``).
    """
    from resloc.runtime.team import team_setup

    for ep in listen:
        check_endpoint(ep, "--listen")
    for ep in options.connect:
        check_endpoint(ep, "--connect")
    load_or_create_key(options.key_file)
    team = team_setup(options)
    bad = [b for b in external if not 0 <= b < team.robots]
    if bad:
        from resloc.errors import ConfigError

        raise ConfigError(f"--external-robots {bad[0]}: the team has robots 0..{team.robots - 1}")
    steps = team.steps
    if options.replay:
        options.robots, options.replay_steps = team.robots, team.steps
    work = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="resloc-swarm-"))
    work.mkdir(parents=True, exist_ok=True)
    if not listen and not options.connect:
        listen = [free_endpoint()]
    hub = open_session("router", listen, list(options.connect)) if listen else None
    if not options.connect:
        options.connect = [ep.replace("0.0.0.0", "127.0.0.1") for ep in listen]
    options.run_id = options.run_id or uuid.uuid4().hex[:8]
    opts_path = options.save(work / "swarm.json")
    key = load_or_create_key(options.key_file)
    bus = None
    procs: dict[str, subprocess.Popen] = {}
    interrupted = False
    end = ""
    written = False
    try:
        session = open_session("client", [], list(options.connect))
        bus = Bus(session, options.run_id, Codec(key, SUPERVISOR), Verifier(key, options.max_age_s))
        bus.subscribe(bus.key("control", "*"))
        for role in ("recorder", "radio", "world"):
            procs[role] = spawn(role, opts_path, None, work / f"{role}.log")
        K = max(1, int(robots_per_process))
        local = [b for b in range(team.robots) if b not in set(external)]
        for lo in range(0, len(local), K):
            group = local[lo : lo + K]
            ids = ",".join(str(b) for b in group)
            procs[f"robots {ids}"] = spawn("robot", opts_path, ids, work / f"robot-{group[0]}.log")
        while not written:
            try:
                item = bus.get(0.2)
                if item is not None:
                    msg = bus.open(item)
                    if msg is not None and msg.kind is Kind.CONTROL:
                        cmd = msg.body["cmd"]
                        if cmd == "progress" and progress is not None:
                            progress(msg.body["n"], steps)
                        if cmd == "progress" and watch is not None:
                            watch(msg.body["n"], procs)
                        elif cmd == "end":
                            end = msg.body["arg"]
                        elif cmd == "written":
                            written = True
                rec = procs["recorder"].poll()
                if rec is not None and not written:
                    if rec == 0:  # it wrote and left; its notice was lost on the way
                        break
                    end = "recorder process lost"
                    break
                if procs["world"].poll() is not None and not end:
                    # a world that died without its end notice: the recorder sees its token go
                    # and writes what it has; wait for it (bounded)
                    end = "world process lost"
                    deadline = time.monotonic() + 20.0
                    while procs["recorder"].poll() is None and time.monotonic() < deadline:
                        time.sleep(0.1)
                    break
            except KeyboardInterrupt:
                if interrupted:  # a second Ctrl-C: stop waiting
                    end = end or "interrupted"
                    break
                interrupted = True
                bus.send(
                    bus.key("control", "world"),
                    Kind.CONTROL,
                    0,
                    {"cmd": "stop", "arg": "", "n": 0},
                )
    finally:
        codes = {}
        for name, proc in procs.items():
            try:
                codes[name] = stop_process(proc, 10.0 if name == "recorder" else 5.0)
            except KeyboardInterrupt:
                codes[name] = stop_process(proc, 0.5)
        if bus is not None:
            bus.close()
        if hub is not None:
            hub.close()
    out = Path(options.out)
    runtime = _read_json(out / "runtime.json")
    summary = _read_json(out / "summary.json")
    if not end.endswith("lost"):  # the recorder's account, unless it or the world died
        end = runtime.get("end") or end or "unknown"
    result = SwarmResult(out, end, runtime, summary, interrupted, codes, work)
    if end != "complete" and not end.startswith("interrupted"):
        logs = "; ".join(
            f"{n}: {_tail(work / f)}"
            for n, f in (("world", "world.log"), ("recorder", "recorder.log"))
            if _tail(work / f)
        )
        raise SwarmError(
            f"run ended early: {end}; partial results in {out}/"
            + (f" (logs in {work}: {logs})" if logs else f" (logs in {work})")
        )
    return result


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
