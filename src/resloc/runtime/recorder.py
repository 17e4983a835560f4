"""The recorder process: the outputs and metrics of ``resloc run``, plus the wire.

It collects the world's truth, every robot's reports and the radio's wire statistics, and
writes, atomically (:func:`~resloc.experiments.output.atomic_output_dir`), the files of
``resloc run`` (:func:`~resloc.experiments.run_files.save_run`: ``scenario.toml``,
``summary.json``, ``timeseries.csv``, ``trajectories.csv``, ``transmissions_<filter>.csv``,
figures) computed by the runner's own per-step bookkeeping, and the runtime's own:

* ``runtime.json``: how the run ended, steps completed, per-kind messages and bytes per robot
  per second beside the trigger's communication rate, rejected frames by reason and
  process, late/stale/unheard counts, re-joins and each re-joined robot's error after;
* ``wire.csv``: per robot and kind: messages, bytes, delivered and lost copies, rates;
* ``robot_errors.csv``: per step and robot, position error (m) and whether it was fed;
* ``estimates.npz``: reported estimates ``x: (K+1, N, 3)`` and covariances ``P: (K+1, N,
  3, 3)`` at full precision.

While the run goes on it rewrites a partial snapshot every ``checkpoint_s`` seconds, so a
lost recorder leaves the results up to its last snapshot; a lost world ends the run with the
results so far.
"""

from __future__ import annotations

import collections
import csv
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from resloc.cl.step import LinkOutcome
from resloc.experiments.output import atomic_output_dir
from resloc.experiments.run_files import save_run, write_json
from resloc.runtime.messages import (
    FLAG_DELIVERED,
    FLAG_DETECTED,
    FLAG_FUSED,
    FLAG_REPAIRED,
    FLAG_TRIGGERED,
    RECORDER,
    Kind,
    Message,
)
from resloc.runtime.options import Mode, SwarmOptions
from resloc.runtime.process import EXIT_LOST, EXIT_OK, connect_bus
from resloc.runtime.team import team_setup
from resloc.signals import held

__all__ = ["Recording", "run_recorder"]

KIND_NAMES = {
    int(Kind.ESTIMATE): "estimate",
    int(Kind.ACK): "ack",
    int(Kind.CONSENSUS): "consensus",
    int(Kind.REQUEST): "request",
    int(Kind.REPLY): "reply",
}


class Recording:
    """Everything received, and the result assembled from it."""

    def __init__(self, options: SwarmOptions) -> None:
        self.options = options
        self.team = team_setup(options)
        self.n = self.team.robots
        self.x0 = np.full((self.n, 3), np.nan)
        self.P0 = np.full((self.n, 3, 3), np.nan)
        self.truth: dict[int, dict] = {}
        self.truth_time: dict[int, float] = {}
        self.reports: dict[int, dict[int, dict]] = collections.defaultdict(dict)
        self.counters: dict[int, dict] = {}
        self.wire: collections.Counter = collections.Counter()
        self.radio_counts: dict = {}
        self.rejoins: list[dict] = []
        self.end_reason = ""
        self.started = time.monotonic()

    def take(self, msg: Message) -> None:
        b = msg.body
        if msg.kind is Kind.START:
            r = int(b["robot"])
            if b["rejoin"]:
                self.rejoins.append({"robot": r, "step": msg.step})
            elif 0 <= r < self.n:
                self.x0[r], self.P0[r] = b["x"], b["P"]
        elif msg.kind is Kind.TRUTH:
            self.truth[msg.step] = b
            self.truth_time[msg.step] = time.monotonic()
        elif msg.kind is Kind.REPORT and 0 <= b["robot"] < self.n:
            self.reports[msg.step][int(b["robot"])] = b
            self.counters[int(b["robot"])] = b["cnt"]
        elif msg.kind is Kind.STATS:
            for r, kd, m, by, cp, lo in zip(
                b["robot"], b["kind"], b["msgs"], b["bytes"], b["copies"], b["jammed"], strict=True
            ):
                for f, v in (("msgs", m), ("bytes", by), ("copies", cp), ("lost", lo)):
                    self.wire[(int(r), int(kd), f)] += int(v)
            self.radio_counts = b["cnt"]

    @property
    def steps_done(self) -> int:
        """Consecutive steps with truth whose reports are in: every fed robot reported, or
        the world has moved on (its barrier passed; realtime never waits)."""
        done = 0
        for k in sorted(s for s in self.truth if s > 0):
            if k != done + 1:
                break
            reported = set(self.reports.get(k, {}))
            if k + 1 not in self.truth and not self.end_reason:
                if not {int(r) for r in self.truth[k]["fed"]} <= reported:
                    break
            done = k
        return done

    # ------------------------------------------------------------------ result
    def estimates(self):
        """Reported estimates of the steps so far, carried forward where a robot did not
        report (dead, or late in realtime).

        Returns
        -------
        X : ndarray, shape (K + 1, N, 3)
        P : ndarray, shape (K + 1, N, 3, 3)
        fed : ndarray of bool, shape (K + 1, N)
            The robot reported this step.
        truth : ndarray, shape (K + 1, N, 3)
        missing : int
            Reports of fed robots that never came.
        """
        K, N = self.steps_done, self.n
        X = np.empty((K + 1, N, 3))
        P = np.empty((K + 1, N, 3, 3))
        X[0], P[0] = self.x0, self.P0
        fed = np.zeros((K + 1, N), dtype=bool)
        truth = np.empty((K + 1, N, 3))
        truth[0] = self.truth[0]["pose"] if 0 in self.truth else np.nan
        missing = 0
        for k in range(1, K + 1):
            truth[k] = self.truth[k]["pose"]
            X[k], P[k] = X[k - 1], P[k - 1]
            for r in self.truth[k]["fed"]:
                rep = self.reports.get(k, {}).get(int(r))
                if rep is None:
                    missing += 1
                    continue
                fed[k, r] = True
                X[k, r], P[k, r] = rep["x"], rep["P"]
        return X, P, fed, truth, missing

    def run_result(self, X: np.ndarray, P: np.ndarray):
        """The :class:`~resloc.experiments.runner.RunResult` of the steps so far, its
        metrics computed by the runner's own per-step bookkeeping."""
        from resloc.experiments.runner import (
            EstimatorResult,
            EstimatorTrack,
            RunResult,
            record_step,
        )

        K, N, name = self.steps_done, self.n, self.team.filter_name
        scenario = self.team.scenario.replace(
            **{"run.steps": max(K, 1), "run.filters": [name], "run.dead_reckoning": False}
        )
        tr = EstimatorTrack(name, None, self.x0, self.P0, K, 1, N)
        for k in range(1, K + 1):
            t = self.truth[k]
            i, j = t["i"], t["j"]
            E = len(i)
            flags = np.zeros(E, dtype=np.uint8)
            norm = np.full(E, np.nan)
            row = {(int(a), int(c)): e for e, (a, c) in enumerate(zip(i, j, strict=True))}
            for r, rep in self.reports.get(k, {}).items():
                for c, f, nv in zip(rep["j"], rep["flags"], rep["norm"], strict=True):
                    e = row.get((int(r), int(c)))
                    if e is not None:
                        flags[e], norm[e] = f, nv
            out = LinkOutcome(
                norm,
                np.full(E, np.nan),
                (flags & FLAG_DETECTED) > 0,
                (flags & FLAG_TRIGGERED) > 0,
                (flags & FLAG_DELIVERED) > 0,
                (flags & FLAG_FUSED) > 0,
                (flags & FLAG_REPAIRED) > 0,
            )
            tr.x, tr.P = X[k], P[k]
            ws = SimpleNamespace(pose=t["pose"], i=i, j=j, attacked=t["att"].astype(bool))
            attacked = np.array([ws.attacked.sum()])
            record_step(
                tr, None, k - 1, ws, out, np.zeros(E, np.int64), np.array([E]), attacked, 1, N, True
            )
        est = EstimatorResult(name, tr.series, tr.totals, tr.raster, tr.track)
        return RunResult(
            scenario,
            {name: est},
            self._truth_array(K),
            self.team.dt * np.arange(1, K + 1),
            time.monotonic() - self.started,
            {"robots": N, "trials": 1},
        )

    def _truth_array(self, K: int) -> np.ndarray:
        return np.stack([self.truth[k]["pose"] for k in range(K + 1)])

    def trigger_counts(self) -> tuple[int, int]:
        """Sensed links (candidates) and attempted transmissions the robots reported."""
        K = self.steps_done
        candidates = sum(len(self.truth[k]["i"]) for k in range(1, K + 1))
        triggered = sum(
            int(((rep["flags"] & FLAG_TRIGGERED) > 0).sum())
            for k in range(1, K + 1)
            for rep in self.reports.get(k, {}).values()
        )
        return candidates, triggered

    def runtime_summary(self, X, fed, truth, missing, msle_mean: float) -> dict:
        K, N, dt = self.steps_done, self.n, self.team.dt
        seconds = max(K * dt, 1e-12)
        by_kind = {}
        for kd, name in KIND_NAMES.items():
            msgs = sum(self.wire[(r, kd, "msgs")] for r in range(N))
            byts = sum(self.wire[(r, kd, "bytes")] for r in range(N))
            by_kind[name] = {
                "messages_per_robot_per_s": msgs / N / seconds,
                "bytes_per_robot_per_s": byts / N / seconds,
                "messages": msgs,
                "bytes": byts,
                "copies_delivered": sum(self.wire[(r, kd, "copies")] for r in range(N)),
                "copies_lost": sum(self.wire[(r, kd, "lost")] for r in range(N)),
            }
        by_kind["total"] = {
            f: sum(v[f] for v in by_kind.values())
            for f in ("messages_per_robot_per_s", "bytes_per_robot_per_s", "messages", "bytes")
        }
        candidates, triggered = self.trigger_counts()
        err = np.hypot(*(X[:, :, :2] - truth[:, :, :2]).transpose(2, 0, 1))
        rejoin = []
        for ev in self.rejoins:
            r, k0 = ev["robot"], ev["step"]
            ks = [k for k in range(k0 + 1, K + 1) if fed[k, r]]
            rejoin.append(
                {
                    "robot": r,
                    "step": k0,
                    "error_m_after": [
                        [k - k0, float(err[k, r])] for k in ks[:: max(len(ks) // 50, 1)]
                    ],
                    "error_m_final": float(err[K, r]) if ks else None,
                }
            )
        counts: collections.Counter = collections.Counter()
        for c in self.counters.values():
            counts.update({k: v for k, v in c.items() if k != "cpu_ms_process"})
        # CPU seconds of each robot's process since its START (shared by its K robots)
        cpu = {str(r): c.get("cpu_ms_process", 0) / 1000.0 for r, c in self.counters.items()}
        walls = [
            self.truth_time[k] - self.truth_time[k - 1]
            for k in range(2, K + 1)
            if k in self.truth_time and k - 1 in self.truth_time
        ]
        return {
            "schema_version": 1,
            "mode": self.options.mode.value,
            "end": self.end_reason or f"running (snapshot after step {K})",
            "partial": self.end_reason != "complete" or K < self.team.steps,
            "steps_completed": K,
            "steps_planned": self.team.steps,
            "robots": N,
            "dt_s": dt,
            "jam_acks": self.options.jam_acks,
            "estimates": "pulled on trigger" if self.team.pull else "broadcast every step",
            "max_age_steps": self.options.max_age_steps,
            "wall_time_per_step_s": {
                "mean": float(np.mean(walls)) if walls else None,
                "median": float(np.median(walls)) if walls else None,
                "p95": float(np.percentile(walls, 95)) if walls else None,
            },
            "wire_by_kind": by_kind,
            "trigger": {
                "comm_rate": triggered / candidates if candidates else None,
                "triggered_links_per_robot_per_s": triggered / N / seconds,
                "candidates": candidates,
                "transmissions": triggered,
            },
            "robot_counters": dict(counts),
            "radio_rejected": {k: v for k, v in self.radio_counts.items() if k != "cpu_ms"},
            "radio_cpu_s": self.radio_counts.get("cpu_ms", 0) / 1000.0,
            "missing_reports": missing,
            "cpu_s_by_robot_process": cpu,
            "cpu_per_step_ms_by_robot_process": {r: 1000 * v / max(K, 1) for r, v in cpu.items()},
            "rejoins": rejoin,
            "msle_mean": msle_mean,
        }

    def lockstep_msle(self) -> float | None:
        """Realtime runs: the MSLE of the same scenario, seed and steps in lockstep, i.e. of
        the in-process simulator (which a lockstep swarm equals to 1e-9), to report beside
        the realtime MSLE. None for lockstep runs and replays."""
        if self.options.mode is Mode.LOCKSTEP or self.team.scenario is None:
            return None
        from resloc.experiments.runner import run_scenario

        sc = self.team.scenario.replace(
            **{
                "run.steps": self.steps_done,
                "run.filters": [self.team.filter_name],
                "run.dead_reckoning": False,
            }
        )
        return run_scenario(sc).summary()[self.team.filter_name]["msle_mean"]

    def save(self, out: Path, plots: bool, overwrite: bool, final: bool = False) -> bool:
        """Write everything received so far into ``out`` (atomically). False if no step."""
        if self.steps_done < 1 or np.isnan(self.x0).any():
            with atomic_output_dir(out, overwrite) as tmp:
                write_json(tmp / "runtime.json", {"end": self.end_reason, "steps_completed": 0})
            return False
        X, P, fed, truth, missing = self.estimates()
        name = self.team.filter_name
        with atomic_output_dir(out, overwrite) as tmp:
            if self.team.mrclam is not None:  # scored against the dataset's ground truth
                from resloc.experiments.mrclam import save_mrclam
                from resloc.runtime.replay import score_replay

                wall = time.monotonic() - self.started
                result = score_replay(
                    self.team, self.options.replay, X, P, self.reports, self.steps_done, wall
                )
                save_mrclam(result, tmp, plots=plots)
            else:
                result = self.run_result(X, P)
                save_run(result, tmp, plots=plots)
            msle_mean = result.summary()[name]["msle_mean"]
            summary = self.runtime_summary(X, fed, truth, missing, msle_mean)
            if final:
                summary["msle_mean_lockstep"] = self.lockstep_msle()
            write_json(tmp / "runtime.json", summary)
            with held():  # an interrupted savez leaves a ZipFile that prints a traceback
                np.savez_compressed(tmp / "estimates.npz", x=X, P=P, truth=truth, fed=fed)
            self._write_wire(tmp / "wire.csv", self.steps_done * self.team.dt)
            err = np.hypot(*(X[:, :, :2] - truth[:, :, :2]).transpose(2, 0, 1))
            with (tmp / "robot_errors.csv").open("w", newline="", encoding="utf-8") as fh:
                w = csv.writer(fh)
                w.writerow(["step", "robot", "position_error_m", "fed"])
                for k in range(len(X)):
                    for r in range(self.n):
                        w.writerow([k, r, f"{err[k, r]:.6g}", int(fed[k, r])])
        return True

    def _write_wire(self, path: Path, seconds: float) -> None:
        with path.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(
                [
                    "robot",
                    "kind",
                    "messages",
                    "bytes",
                    "copies_delivered",
                    "copies_lost",
                    "messages_per_s",
                    "bytes_per_s",
                ]
            )
            for r in range(self.n):
                for kd, name in KIND_NAMES.items():
                    m, b = self.wire[(r, kd, "msgs")], self.wire[(r, kd, "bytes")]
                    w.writerow(
                        [
                            r,
                            name,
                            m,
                            b,
                            self.wire[(r, kd, "copies")],
                            self.wire[(r, kd, "lost")],
                            f"{m / max(seconds, 1e-12):.6g}",
                            f"{b / max(seconds, 1e-12):.6g}",
                        ]
                    )


def run_recorder(options: SwarmOptions) -> int:
    """Run the recorder until the world ends the run (or is lost); write the outputs."""
    bus = connect_bus(options, RECORDER)
    rec = Recording(options)
    out = Path(options.out)
    code = EXIT_OK
    try:
        bus.subscribe(bus.key("recorder", "*"))
        bus.subscribe(bus.key("report", "*"))
        bus.subscribe(bus.key("robot", "*", "start"))
        bus.subscribe(bus.key("control", "end"))
        bus.watch_liveliness(bus.key("alive", "world"))
        bus.declare_alive(bus.key("alive", "recorder"))
        last_save, saved_steps, world_seen = time.monotonic(), 0, False
        interval = options.checkpoint_s
        overwrite = options.overwrite
        while not rec.end_reason:
            item = bus.get(0.25)
            if item is not None:
                tag, _, payload = item
                if tag == "alive":
                    world_seen = world_seen or payload
                    if not payload and world_seen:
                        rec.end_reason = f"world process lost after step {rec.steps_done}"
                        code = EXIT_LOST
                    continue
                msg = bus.open(item)
                if msg is None:
                    continue
                if msg.kind is Kind.CONTROL and msg.body["cmd"] == "end":
                    rec.end_reason = msg.body["arg"]
                    # the last step's reports may still be in flight
                    drain_end = time.monotonic() + 0.5
                    while time.monotonic() < drain_end:
                        more = bus.get(0.05)
                        if more is not None and more[0] == "frame":
                            m2 = bus.open(more)
                            if m2 is not None:
                                rec.take(m2)
                else:
                    rec.take(msg)
            now = time.monotonic()
            if now - last_save > interval and rec.steps_done > saved_steps:
                rec.save(out, plots=False, overwrite=True if saved_steps else overwrite)
                saved_steps, last_save = rec.steps_done, time.monotonic()
                # a long run's snapshot takes longer: never spend over a tenth of the time on it
                interval = max(options.checkpoint_s, 10.0 * (last_save - now))
        rec.save(out, plots=options.plots, overwrite=True if saved_steps else overwrite, final=True)
        bus.send(
            bus.key("control", "recorder"),
            Kind.CONTROL,
            rec.steps_done,
            {"cmd": "written", "arg": str(out), "n": rec.steps_done},
        )
        time.sleep(0.1)
        return code
    finally:
        bus.close()
