"""``resloc attack``: every defence against every attacker of the adversary suite."""

from __future__ import annotations

import datetime as _dt
import sys
from pathlib import Path

import typer

from resloc.cli.common import fail, handle_errors
from resloc.cli.study import FRESH, JOBS, SCHEDULER, STORE, study_session, write_failures

__all__ = ["attack_command", "parse_attacker", "parse_defence", "register"]


def parse_defence(text: str) -> tuple[str, dict]:
    """``NAME`` (a built-in defence) or ``NAME:key=value,key=value`` (dotted overrides;
    values parsed as TOML scalars). Raises ``ValueError`` with a one-line reason."""
    from resloc.experiments.defences import DEFENCES

    name, _, spec = text.partition(":")
    name = name.strip()
    if not spec:
        if name not in DEFENCES:
            raise ValueError(
                f"--defence {name!r}: unknown; use one of {', '.join(DEFENCES)} or "
                "NAME:key=value,..."
            )
        return name, dict(DEFENCES[name])
    return name, _key_values(text, spec, "--defence")


def _key_values(text: str, spec: str, option: str) -> dict:
    """``key=value,...`` with values parsed as TOML scalars (else kept as strings)."""
    import tomllib

    out = {}
    for item in spec.split(","):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"{option} {text!r}: {item!r} is not key=value")
        try:
            out[key.strip()] = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = value.strip()
    return out


def parse_attacker(text: str) -> str | tuple[str, dict]:
    """``NAME`` (searched over its grid) or ``NAME:key=value,...`` (those parameters only).
    Raises ``ValueError`` with a one-line reason."""
    from resloc.world.attackers import ATTACKERS, make_attacker

    name, _, spec = text.partition(":")
    name = name.strip()
    if name not in ATTACKERS:
        raise ValueError(f"--attacker {name!r}: unknown; use one of {', '.join(ATTACKERS)}")
    if not spec:
        return name
    params = _key_values(text, spec, "--attacker")
    try:
        make_attacker(name, **params)
    except ValueError as exc:
        raise ValueError(f"--attacker {text!r}: {exc}") from None
    return name, params


def attack_command(
    scenario_path: Path | None,
    defences: list[str] | None,
    attackers: list[str] | None,
    seeds: int,
    steps: int | None,
    out: Path | None,
    overwrite: bool,
    progress: bool,
    jobs: int | None = None,
    scheduler: str | None = None,
    store: Path | None = None,
    fresh: bool = False,
    search: bool = True,
):
    """Run the study, print the worst cases, write ``attack.md``/``.csv``/``.json``."""
    from resloc.experiments.attack import run_attack_study
    from resloc.experiments.attack_report import markdown, save_attack_study
    from resloc.experiments.config import default_scenario
    from resloc.experiments.config_parse import load_scenario
    from resloc.experiments.executor import StudyFailedError
    from resloc.experiments.output import atomic_output_dir, check_output_dir

    chosen = None
    if defences:
        try:
            chosen = dict(parse_defence(d) for d in defences)
        except ValueError as exc:
            raise fail(str(exc)) from None
    try:
        chosen_attackers = [parse_attacker(a) for a in attackers or ()]
    except ValueError as exc:
        raise fail(str(exc)) from None
    scenario = default_scenario() if scenario_path is None else load_scenario(scenario_path)
    if steps is not None:
        scenario = scenario.replace(**{"run.steps": int(steps)})
    if chosen:
        for name, ov in chosen.items():
            try:
                scenario.replace(**ov)
            except Exception as exc:  # a bad dotted key: one line naming it
                raise fail(f"--defence {name}: {exc}") from None
    if out is None:
        out = Path("runs") / f"attack-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    check_output_dir(out, overwrite)
    try:
        with study_session("attacking", jobs, scheduler, store, fresh, progress) as study:
            result = run_attack_study(
                scenario, chosen, chosen_attackers or None, seeds=seeds, study=study, search=search
            )
    except StudyFailedError as exc:
        raise write_failures(exc, out, overwrite) from None
    print(markdown(result))
    with atomic_output_dir(out, overwrite) as tmp:
        save_attack_study(result, tmp)
    print(f"results written to {out}/ (attack.md, attack.csv, attack.json)")
    return result


def register(app: typer.Typer) -> None:
    """Add ``attack`` to ``app``."""

    @app.command("attack")
    @handle_errors
    def attack(
        scenario: Path | None = typer.Argument(
            None, help="Scenario TOML (default: the embedded one)."
        ),
        defence: list[str] | None = typer.Option(
            None,
            "--defence",
            "-d",
            help="A defence: a built-in name or NAME:key=value,... (repeat; default: all "
            "built-in).",
        ),
        attacker: list[str] | None = typer.Option(
            None,
            "--attacker",
            "-a",
            help="An attacker of the suite, searched over its grid, or NAME:key=value,... "
            "for those parameters only (repeat; default: all).",
        ),
        seeds: int = typer.Option(10, "--seeds", min=2, help="Paired seeds per cell."),
        search: bool = typer.Option(
            True,
            "--search/--no-search",
            help="Run every attacker at every point of its parameter grid and report the "
            "worst (--no-search: default parameters only).",
        ),
        steps: int | None = typer.Option(None, "--steps", min=1, help="Override run.steps."),
        jobs: int | None = JOBS,
        scheduler: str | None = SCHEDULER,
        store: Path | None = STORE,
        fresh: bool = FRESH,
        out: Path | None = typer.Option(
            None, "--out", "-o", help="Output directory \\[default: runs/attack-<timestamp>]."
        ),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out."),
        progress: bool = typer.Option(
            True, "--progress/--no-progress", help="Show a progress bar on stderr."
        ),
    ) -> None:
        """Every defence against every attacker of the adversary suite (each knows the
        defence it faces): MSLE ratio to the clean run per seed, NEES, TPR/FPR, worst case."""
        attack_command(
            scenario,
            defence,
            attacker,
            seeds,
            steps,
            out,
            overwrite,
            progress and sys.stderr.isatty(),
            jobs,
            scheduler,
            store,
            fresh,
            search,
        )
