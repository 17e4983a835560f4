"""Never crash, never lose a result: one-line usage errors, --out checked before any work,
divergence isolation, plots that fail, leftovers of killed runs, atomic --overwrite."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from resloc.cli.app import app
from resloc.experiments import output

runner = CliRunner()
FIXTURE = Path(__file__).parent / "fixtures" / "mrclam" / "MRCLAM_Dataset6_60s"

TINY = """
[run]
steps = 30
filters = ["ckf", "ekf"]
[team]
robots = 4
"""


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(TINY)
    return p


def _err_lines(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.strip()]


def _one_error_line(res, needle: str = "") -> str:
    lines = _err_lines(res)
    assert res.exit_code == 2, (res.exit_code, res.output)
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert needle in lines[0], lines[0]
    assert "Traceback" not in res.output
    return lines[0]


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait(timeout=30)
    return proc.pid


@pytest.fixture
def no_compute(monkeypatch):
    """Make every computation fail loudly: a check that passes lets the test see it."""

    def boom(*args, **kwargs):
        raise AssertionError("computation started before --out was checked")

    import resloc.experiments.compare as compare
    import resloc.experiments.mrclam as mrclam
    import resloc.experiments.reproduce as reproduce
    import resloc.experiments.runner as runner_mod
    import resloc.experiments.sweep as sweep

    monkeypatch.setattr(runner_mod, "run_scenario", boom)
    monkeypatch.setattr(mrclam, "run_mrclam", boom)
    monkeypatch.setattr(sweep, "run_sweep", boom)
    monkeypatch.setattr(reproduce, "run_reproduction", boom)
    monkeypatch.setattr(compare, "run_compare", boom)


# ---------------------------------------------------------------------------- usage errors
@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["run", "--seed", "-4"], "resloc run: Invalid value for '--seed'"),
        (["run", "--seed", str(10**40)], "resloc run: Invalid value for '--seed'"),
        (["run", "--filter", "kalman"], "'kalman' is not one of"),
        (["run", "--bogus"], "No such option: --bogus"),
        (["bogus"], "No such command 'bogus'"),
        (["mrclam"], "resloc mrclam: Missing argument 'path'"),
        (["mrclam", str(FIXTURE), "--seed", str(2**63)], "Invalid value for '--seed'"),
        (["mrclam", str(FIXTURE), "--dt", "abc"], "Invalid value for '--dt'"),
        (["sweep"], "resloc sweep: Missing argument"),
        (["reproduce", "--jobs", "0"], "resloc reproduce: Invalid value for '--jobs'"),
        (["scenario", "shw"], "Did you mean 'show'"),
    ],
)
def test_framework_usage_errors_are_one_line(args, needle):
    res = runner.invoke(app, args)
    _one_error_line(res, needle)


def test_usage_error_in_a_real_process_is_one_line():
    proc = subprocess.run(
        [sys.executable, "-c", "from resloc.cli.app import main; main()", "run", "--seed", "-4"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: resloc run: Invalid value"), proc.stderr


def test_no_arguments_still_prints_the_help():
    res = runner.invoke(app, [])
    assert "Usage" in res.output and "run" in res.output


# ---------------------------------------------------------------------------- --out checks
def _out_cases(tmp_path: Path) -> list[tuple[str, str]]:
    afile = tmp_path / "afile"
    afile.write_text("x")
    return [
        (".", "is the current directory"),
        (str(afile / "sub"), "is a file, not a directory"),
        (str(tmp_path / ("n" * 250)), "is too long"),
        ("/proc/resloc-cannot-write-here", "cannot create a directory"),
        (str(afile), "exists and is not a directory"),
    ]


@pytest.mark.parametrize("case", range(5))
@pytest.mark.parametrize("command", ["run", "mrclam", "sweep", "reproduce", "compare"])
def test_out_is_checked_before_any_computation(
    command, case, tmp_path, tiny, no_compute, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    out, needle = _out_cases(tmp_path)[case]
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(TINY + '[sweep]\nparameter = "detector.rho"\nvalues = [0.5, 1.0]\n')
    args = {
        "run": ["run", str(tiny)],
        "mrclam": ["mrclam", str(FIXTURE)],
        "sweep": ["sweep", str(sweep)],
        "reproduce": ["reproduce", "--quick"],
        "compare": ["compare", "--quick"],
    }[command]
    res = runner.invoke(app, [*args, "--out", out])
    _one_error_line(res, needle)


def test_out_inside_an_input_or_holding_it(tmp_path, tiny, no_compute):
    res = runner.invoke(app, ["mrclam", str(FIXTURE), "--out", str(FIXTURE / "results")])
    _one_error_line(res, "lies inside the input")
    # --overwrite of the folder that holds the scenario would delete the scenario.
    res = runner.invoke(app, ["run", str(tiny), "--out", str(tmp_path), "--overwrite"])
    _one_error_line(res, "which --overwrite would delete")
    assert tiny.exists()


# ---------------------------------------------------------------------------- isolation
def test_a_diverging_filter_is_reported_and_the_others_are_written(tmp_path):
    scenario = tmp_path / "ukf.toml"
    scenario.write_text("[run]\nsteps = 120\n[team]\nrobots = 5\ninit_heading_std = 1.5\n")
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(scenario), "--out", str(out), "--no-plots"])
    assert res.exit_code == 0, res.output
    warnings = [ln for ln in _err_lines(res) if ln.startswith("warning: UKF diverged at step")]
    assert len(warnings) == 1 and "robot" in warnings[0] and "trial 0" in warnings[0]
    summary = json.loads((out / "summary.json").read_text())
    d = summary["diverged"]["ukf"]
    assert set(d) >= {"step", "time_s", "trial", "robot", "reason"} and d["step"] >= 1
    assert summary["estimators"]["ukf"]["msle_mean"] is None  # blank, not a partial mean
    for name in ("ckf", "ekf", "dr"):
        assert summary["estimators"][name]["msle_mean"] is not None
        assert name not in summary["diverged"]
    assert "diverged (step" in res.stdout


def test_a_plot_that_cannot_be_drawn_is_skipped_and_the_data_written(tmp_path, tiny, monkeypatch):
    import resloc.experiments.plots as plots

    def broken(result, out):
        raise ValueError("a figure that cannot be drawn")

    monkeypatch.setattr(plots, "plot_run", broken)
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert any(ln.startswith("warning: figures skipped (ValueError") for ln in _err_lines(res)), (
        res.stderr
    )
    assert (out / "summary.json").exists() and not list(out.glob("*.png"))


def test_a_run_name_with_mathtext_and_quotes_plots_and_reloads(tmp_path):
    scenario = tmp_path / "named.toml"
    scenario.write_text(
        '[run]\nname = "gain $\\\\alpha_{x$ \\"q\\" \\\\ end"\nsteps = 20\n[team]\nrobots = 3\n'
    )
    out = tmp_path / "out"
    res = runner.invoke(app, ["run", str(scenario), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "trajectories.png").exists()
    assert not any(ln.startswith("warning") for ln in _err_lines(res))
    again = runner.invoke(app, ["scenario", "show", str(out / "scenario.toml")])
    assert again.exit_code == 0 and 'name = "gain $\\\\alpha_{x$ \\"q\\"' in again.stdout


# ---------------------------------------------------------------------------- leftovers
def test_leftover_temporary_of_a_killed_run_is_removed(tmp_path, tiny):
    out = tmp_path / "out"
    pid = _dead_pid()
    litter = tmp_path / f".out.tmp-{pid}-abcd1234"
    litter.mkdir()
    (litter / "summary.json").write_text("{}")
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert f"note: removed .out.tmp-{pid}-abcd1234" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "tiny.toml"]


def test_old_results_hidden_by_a_kill_between_renames_are_restored(tmp_path, tiny):
    out = tmp_path / "out"
    pid = _dead_pid()
    hidden = tmp_path / f".out.old-{pid}"
    hidden.mkdir()
    (hidden / "precious.txt").write_text("old results")
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out), "--no-plots"])
    # The old results are back under --out, so a run without --overwrite refuses it.
    note, error = _err_lines(res)
    assert res.exit_code == 2 and note.startswith(f"note: restored {out} from .out.old-{pid}")
    assert error.startswith("error: --out") and "directory exists and is not empty" in error
    assert (out / "precious.txt").read_text() == "old results"
    assert not hidden.exists()


def test_leftovers_of_a_live_process_are_left_alone(tmp_path):
    busy = tmp_path / f".out.tmp-{os.getpid()}-zz"
    busy.mkdir()
    assert output.recover_leftovers(tmp_path / "out", log=lambda line: None) == []
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        theirs = tmp_path / f".out.tmp-{other.pid}-zz"
        theirs.mkdir()
        lines = output.recover_leftovers(tmp_path / "out", log=lambda line: None)
        assert lines == [f"{theirs.name} belongs to running process {other.pid}; left alone"]
    finally:
        other.kill()
        other.wait(timeout=30)
    assert busy.exists() and theirs.exists()


@pytest.mark.parametrize("atomic", [True, False])
def test_overwrite_swaps_and_leaves_no_litter(tmp_path, tiny, monkeypatch, atomic):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    calls = []
    real = output._exchange

    def exchange(a, b):
        calls.append((a, b))
        return real(a, b) if atomic else False

    monkeypatch.setattr(output, "_exchange", exchange)
    res = runner.invoke(app, ["run", str(tiny), "--out", str(out), "--no-plots", "--overwrite"])
    assert res.exit_code == 0, res.output
    assert len(calls) == 1
    assert (out / "summary.json").exists() and not (out / "old.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "tiny.toml"]


def test_renameat2_exchange_is_atomic_here(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "x").write_text("a")
    (b / "x").write_text("b")
    assert output._exchange(a, b) is True  # Linux: the swap is one system call
    assert (a / "x").read_text() == "b" and (b / "x").read_text() == "a"


def test_a_failure_while_writing_leaves_out_untouched(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), output.atomic_output_dir(out, overwrite=True) as tmp:
        (tmp / "half.csv").write_text("1,2")
        raise RuntimeError("disk full")
    assert [p.name for p in out.iterdir()] == ["old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_a_signal_while_writing_removes_the_temporary(tmp_path, signum):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    stopped = (output.Terminated, KeyboardInterrupt)
    with pytest.raises(stopped), output.atomic_output_dir(out, overwrite=True) as tmp:
        (tmp / "half.csv").write_text("1,2")
        os.kill(os.getpid(), signum)
        time.sleep(5)  # the signal arrives here
    assert [p.name for p in out.iterdir()] == ["old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert signal.getsignal(signal.SIGTERM) is not None  # the previous handler is back


@pytest.mark.parametrize("where", ["probe", "mkdtemp", "rmtree"])
def test_a_signal_inside_making_or_removing_the_temporary_leaves_nothing(
    tmp_path, monkeypatch, where
):
    """A Ctrl-C inside ``mkdtemp`` (after its mkdir: the writability probe's or the
    temporary's) or part-way through removing the swapped-out results left a hidden
    ``.out.tmp-*`` after a clean stop (seen once in CI's kill test): these run with
    signals held, the interrupt raised once the directory is gone."""
    import shutil
    import tempfile

    from resloc.signals import raising_handler

    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    real = {"mkdtemp": tempfile.mkdtemp, "rmtree": shutil.rmtree}
    made = []

    def interrupt() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)  # without the hold, the KeyboardInterrupt is raised here

    def mkdtemp(*args, **kwargs):
        made.append(real["mkdtemp"](*args, **kwargs))
        if len(made) == {"probe": 1, "mkdtemp": 2}.get(where):
            interrupt()
        return made[-1]

    def rmtree(path, *args, **kwargs):
        if where == "rmtree" and (Path(path) / "old.txt").exists():
            interrupt()
        return real["rmtree"](path, *args, **kwargs)

    monkeypatch.setattr(tempfile, "mkdtemp", mkdtemp)
    monkeypatch.setattr(shutil, "rmtree", rmtree)
    # The CLI's Ctrl-C handler (the one signals.held can hold), as `resloc` installs it.
    previous = signal.signal(signal.SIGINT, raising_handler(lambda signum: KeyboardInterrupt()))
    try:
        with pytest.raises(KeyboardInterrupt):
            with output.atomic_output_dir(out, overwrite=True) as tmp:
                (tmp / "new.txt").write_text("new")
    finally:
        signal.signal(signal.SIGINT, previous)
        monkeypatch.undo()
    assert len(made) == {"probe": 1, "mkdtemp": 2, "rmtree": 2}[where]
    assert [p.name for p in out.iterdir()] == ["new.txt" if where == "rmtree" else "old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_signal_as_the_removal_enters_its_hold_still_removes_the_temporary(tmp_path, monkeypatch):
    """A Ctrl-C whose exception is raised as a temporary's removal enters its hold (before
    the hold takes effect) skipped the removal: it is kept, the directory removed, then
    raised."""
    from contextlib import contextmanager

    from resloc import signals

    real_held = signals.held
    entries = []

    @contextmanager
    def held():
        entries.append(len(entries) + 1)
        if len(entries) == 2:  # the removal's (the first: mkdtemp's)
            raise KeyboardInterrupt
        with real_held():
            yield

    monkeypatch.setattr(signals, "held", held)
    with pytest.raises(KeyboardInterrupt):
        with signals.temporary_directory(".out.tmp-", tmp_path) as tmp:
            (tmp / "old.txt").write_text("old")
    monkeypatch.undo()
    assert len(entries) >= 2
    assert list(tmp_path.iterdir()) == []


def test_a_signal_after_the_swap_leaves_no_old_results_behind(tmp_path, monkeypatch):
    """The swapped-out results are removed inside the swap's blocked signals: a Ctrl-C
    handled after the swap, before the temporary's own removal (simulated: that removal
    raises without removing), left them in a hidden ``.out.tmp-*`` (once in a fresh clone's
    kill test)."""
    from resloc import signals

    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")

    def interrupted(path, attempts=3):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with output.atomic_output_dir(out, overwrite=True) as tmp:
            (tmp / "new.txt").write_text("new")
            monkeypatch.setattr(signals, "_remove_held", interrupted)
    monkeypatch.undo()
    assert [p.name for p in out.iterdir()] == ["new.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_mrclam_reports_dropped_and_reordered_rows_and_strict_refuses(tmp_path):
    import shutil

    folder = tmp_path / FIXTURE.name
    shutil.copytree(FIXTURE, folder)
    odo = folder / "Robot2_Odometry.dat"
    rows = [ln for ln in odo.read_text().splitlines() if ln[0] != "#"]
    odo.write_text(odo.read_text() + rows[100] + "\n")  # a repeat, and out of order
    args = ["mrclam", str(folder), "-f", "ekf", "--duration", "30", "--no-plots"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert res.exit_code == 0, res.output
    assert "data rows: 1 dropped (duplicate 1), 1 out of order" in res.stdout
    info = json.loads((tmp_path / "a" / "summary.json").read_text())["info"]
    assert info["rows_skipped_by_file"] == {
        "Robot2_Odometry.dat": {"duplicate": 1, "out_of_order": 1}
    }
    res = runner.invoke(app, [*args, "--strict", "--out", str(tmp_path / "b")])
    line = _one_error_line(res, "Robot2_Odometry.dat:")
    assert "--strict" in line and not (tmp_path / "b").exists()


def test_a_signal_during_a_finalizer_is_raised_after_it_not_lost(monkeypatch):
    from resloc.signals import raising_handler

    class StopError(Exception):
        pass

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    previous = signal.signal(signal.SIGUSR1, raising_handler(lambda signum: StopError()))
    finished = []

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGUSR1)
            total = 0
            for k in range(10_000):  # bytecodes during which the signal is pending
                total += k
            finished.append(total)

    try:
        with pytest.raises(StopError):
            obj = Finalized()
            del obj
            for _ in range(1000):
                time.sleep(0.001)
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert finished == [sum(range(10_000))] and unraisable == []


def test_a_signal_during_a_callback_from_c_is_raised_after_it_not_lost():
    """numba's compiler calls Python back through ctypes; an exception raised there cannot
    propagate (it goes to sys.unraisablehook): the signal must be raised once it returns."""
    import ctypes

    from resloc.signals import raising_handler

    class StopError(Exception):
        pass

    previous_hook = sys.unraisablehook
    unraisable = []
    sys.unraisablehook = unraisable.append
    previous = signal.signal(signal.SIGUSR1, raising_handler(lambda signum: StopError()))
    finished = []

    @ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int)
    def callback(n):
        os.kill(os.getpid(), signal.SIGUSR1)
        total = 0
        for k in range(n):  # bytecodes during which the signal is pending
            total += k
        finished.append(total)
        return 0

    try:
        with pytest.raises(StopError):
            callback(10_000)  # called from C, as llvmlite calls numba's cache callback
            for _ in range(1000):
                time.sleep(0.001)
    finally:
        signal.signal(signal.SIGUSR1, previous)
        sys.unraisablehook = previous_hook
    assert finished == [] or finished == [sum(range(10_000))]
    assert unraisable == []


def test_a_signal_wrapped_by_an_import_stops_the_command_with_one_line(capsys):
    """A Ctrl-C while a module defines a dataclass arrives as a RuntimeError whose cause is
    the KeyboardInterrupt (``__set_name__``): one line and exit 130, as a bare Ctrl-C."""
    import typer

    from resloc.cli.common import EXIT_INTERRUPTED, handle_errors

    @handle_errors
    def importing():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise RuntimeError("Error calling __set_name__ on 'Field' instance") from exc

    with pytest.raises(typer.Exit) as stop:
        importing()
    assert stop.value.exit_code == EXIT_INTERRUPTED["SIGINT"] == 130
    assert capsys.readouterr().err == "error: interrupted (SIGINT); --out left as it was\n"

    @handle_errors
    def broken():
        raise RuntimeError("a bug, not a signal")

    with pytest.raises(RuntimeError, match="a bug"):  # anything else is not swallowed
        broken()

    @handle_errors
    def own_exit():  # a command's own exit after it handled a signal keeps its code
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise typer.Exit(143) from None

    with pytest.raises(typer.Exit) as stop:
        own_exit()
    assert stop.value.exit_code == 143


def test_an_estimate_worse_than_dead_reckoning_is_warned(tmp_path):
    """The literal summed update double-counts the prior with many neighbours and ends far
    above dead reckoning's MSLE: the run succeeds, with one warning line per such filter."""
    scenario = tmp_path / "summed.toml"
    scenario.write_text(
        '[run]\nsteps = 200\nfilters = ["ckf"]\n[estimator]\nupdate_mode = "summed"\n'
    )
    res = runner.invoke(app, ["run", str(scenario), "--out", str(tmp_path / "a"), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert any(ln.startswith("warning: CKF's mean MSLE") for ln in _err_lines(res)), res.output
    scenario.write_text('[run]\nsteps = 200\nfilters = ["ckf"]\n')
    res = runner.invoke(app, ["run", str(scenario), "--out", str(tmp_path / "b"), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert not any("above dead reckoning" in ln for ln in _err_lines(res)), res.output


def test_a_signal_during_a_held_block_is_raised_when_it_ends():
    from resloc.signals import held, raising_handler

    class StopError(Exception):
        pass

    previous = signal.signal(signal.SIGUSR1, raising_handler(lambda signum: StopError()))
    reached = []
    try:
        with pytest.raises(StopError):
            with held():
                with held():  # nested: raised when the outermost ends
                    os.kill(os.getpid(), signal.SIGUSR1)
                    time.sleep(0.05)
                reached.append("inner")
                time.sleep(0.05)
                reached.append("outer")
        # Nothing left pending: a later block ends quietly.
        with held():
            reached.append("later")
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert reached == ["inner", "outer", "later"]


def test_a_signal_inside_the_recordings_zip_write_leaves_a_whole_file_and_no_traceback(
    tmp_path, monkeypatch
):
    """A signal in numpy's zip member ``close`` left a ZipFile with an open write handle
    whose ``__del__`` printed a traceback (Ctrl-C during ``resloc run``): the save holds it
    until the file is whole, then raises it."""
    import gc
    import zipfile

    import numpy as np

    from resloc.experiments.recording import Recording
    from resloc.signals import raising_handler

    class StopError(Exception):
        pass

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    close = zipfile._ZipWriteFile.close

    def signalled_close(self):
        os.kill(os.getpid(), signal.SIGUSR1)
        for _ in range(1000):  # bytecodes during which the signal is handled
            pass
        close(self)

    monkeypatch.setattr(zipfile._ZipWriteFile, "close", signalled_close)
    rec = Recording(
        name="k",
        source="run",
        t0=0.0,
        time=np.arange(3.0),
        robots=["robot1", "robot2"],
        truth=np.zeros((3, 2, 3)),
        valid=np.ones((3, 2), bool),
        estimates={"ckf": np.ones((3, 2, 3))},
    )
    previous = signal.signal(signal.SIGUSR1, raising_handler(lambda signum: StopError()))
    try:
        with pytest.raises(StopError):
            rec.save(tmp_path / "r.npz")
    finally:
        signal.signal(signal.SIGUSR1, previous)
        monkeypatch.setattr(zipfile._ZipWriteFile, "close", close)
    gc.collect()
    assert unraisable == []
    back = Recording.load(tmp_path / "r.npz")
    assert np.array_equal(back.estimates["ckf"], rec.estimates["ckf"])
