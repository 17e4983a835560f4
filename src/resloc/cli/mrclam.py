"""``resloc mrclam``: replay a UTIAS MRCLAM dataset through the CL estimators."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import enum
import sys
from pathlib import Path

import typer

from resloc.cli.common import FilterChoice, handle_errors, step_progress
from resloc.cli.export import export_option
from resloc.cli.run import warn_diverged
from resloc.innovation_norm import InnovationNorm
from resloc.validation import INT64_MAX

__all__ = ["mrclam_command", "noise_command", "print_mrclam_summary", "register"]


class NoiseChoice(enum.StrEnum):
    """Where the replay's noise model comes from: the built-in defaults (fitted on Dataset 6)
    or a fit of this dataset's sensors against its ground truth (``--estimate-noise``)."""

    DEFAULT = "default"
    AUTO = "auto"


def _fmt(v, spec: str = ".4g") -> str:
    return "-" if v is None or v != v else format(v, spec)


def _fmt_value(v) -> str:
    if isinstance(v, tuple | list):
        return "(" + ", ".join(_fmt(a) for a in v) + ")"
    return _fmt(v)


def print_mrclam_summary(result, console=None) -> None:
    """Print the overall and per-robot tables of an MRCLAM replay."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    info, cfg = result.info, result.config
    title = (
        f"{info['dataset']}: {info['replayed_s']:.1f} s, dt {cfg.dt} s, "
        f"landmarks {'on' if cfg.landmarks else 'off'}, zones {'on' if cfg.zones else 'off'}"
    )
    table = Table(title=title)
    columns = ("estimator", "RMSE m", "head. deg", "MSLE", "NEES", "comm", "prec.", "recall")
    for col in columns:
        table.add_column(col, justify="left" if col == "estimator" else "right")
    for name, s in result.summary().items():
        table.add_row(
            "DR" if name == "dr" else name.upper(),
            f"diverged (step {s['diverged_step']})"
            if s.get("diverged_step")
            else _fmt(s["position_rmse"], ".3f"),
            _fmt(s["heading_rmse_deg"], ".2f"),
            _fmt(s["msle_mean"], ".4f"),
            _fmt(s["nees_mean"], ".3g"),
            _fmt(s["comm_rate"], ".3f"),
            _fmt(s["detector_precision"], ".3f"),
            _fmt(s["detector_recall"], ".3f"),
        )
    console.print(table)
    per = Table(title="position RMSE (m) per robot; DR = dead reckoning (odometry only)")
    per.add_column("estimator")
    for subject in result.robots:
        per.add_column(f"robot {subject}", justify="right")
    for name, est in result.estimators.items():
        per.add_row(
            "DR" if name == "dr" else name.upper(),
            *(_fmt(v, ".3f") for v in est.per_robot["position_rmse"]),
        )
    console.print(per)
    console.print(data_rows_line(info["rows_skipped"]), highlight=False)
    warn_diverged(result.estimators)
    if cfg.zones:
        console.print(
            f"attack layer: {info['attacked']} robot-robot measurements falsified in the SDZ, "
            f"{info['jammed']} transmissions jammed in the CDZ (seed {cfg.seed})"
        )


def data_rows_line(skipped: dict[str, int]) -> str:
    """What loading did to the rows, always printed (zeros too): dropped per reason,
    and reordered."""
    from resloc.datasets.mrclam import DROP_REASONS

    dropped = {k: skipped.get(k, 0) for k in DROP_REASONS if skipped.get(k, 0)}
    total = sum(dropped.values())
    detail = f" ({', '.join(f'{k} {v}' for k, v in dropped.items())})" if dropped else ""
    return (
        f"data rows: {total} dropped{detail}, {skipped.get('out_of_order', 0)} out of order "
        "(sorted, kept); per file in summary.json (info.rows_skipped_by_file)"
    )


#: MRCLAMConfig fields set by a command-line flag of the same name (``--range-std``).
_FLAGS = "dt duration seed rho range_std range_std_rel bearing_std attack_bias sdz cdz".split()


def make_config(**kw):
    """:class:`MRCLAMConfig` from command-line values; errors name the flag."""
    from resloc.errors import ConfigError
    from resloc.experiments.mrclam import MRCLAMConfig

    try:
        return MRCLAMConfig(**kw)
    except ConfigError as exc:
        text = str(exc)
        field = text.split(":", 1)[0].split("[", 1)[0].split(" ", 1)[0]
        if field in _FLAGS:
            text = "--" + field.replace("_", "-") + text[len(field) :]
        raise ConfigError(text) from None


def noise_command(path: Path, duration: float | None, strict: bool = False) -> dict:
    """Print the noise of the dataset's sensors against its ground truth."""
    from rich.console import Console
    from rich.table import Table

    from resloc.datasets.mrclam import load_mrclam
    from resloc.experiments.mrclam import estimate_noise

    data = load_mrclam(path, duration=make_config(duration=duration).duration, strict=strict)
    noise = estimate_noise(data)
    table = Table(title=f"{data.name}: sensor noise against ground truth (std: robust / plain)")
    for col in ("sensor", "n", "range (m)", "range / range", "bearing (rad)"):
        table.add_column(col, justify="left" if col == "sensor" else "right")
    for kind in ("robot", "landmark"):
        s = noise[kind]
        table.add_row(
            f"{kind} sightings",
            str(s["n"]),
            f"{_fmt(s['range_std_robust'], '.3f')} / {_fmt(s['range_std'], '.3f')}",
            _fmt(s["range_std_rel_robust"], ".3f"),
            f"{_fmt(s['bearing_std_robust'], '.4f')} / {_fmt(s['bearing_std'], '.4f')}",
        )
    Console().print(table)
    o = noise["odometry"]
    print(
        f"odometry ({o['n']} windows of 1 s): v density {_fmt(o['v_density'], '.4f')} m/s*sqrt(s) "
        f"(robust {_fmt(o['v_density_robust'], '.4f')}), omega density "
        f"{_fmt(o['omega_density'], '.4f')} rad/s*sqrt(s) "
        f"(robust {_fmt(o['omega_density_robust'], '.4f')})"
    )
    return noise


def mrclam_command(
    path: Path,
    out: Path | None,
    overwrite: bool,
    plots: bool,
    progress: bool,
    export: str | None = None,
    noise: NoiseChoice = NoiseChoice.DEFAULT,
    paper_detector: bool = False,
    **kw,
):
    """Validate, replay, print, save. ``kw`` are :class:`MRCLAMConfig` fields; a field given
    as None takes its default (or, for the noise fields with ``noise = auto``, the fit)."""
    from resloc.cli.export import write_exports
    from resloc.datasets.mrclam import load_mrclam
    from resloc.experiments.mrclam import estimate_noise, noise_from_fit, run_mrclam, save_mrclam
    from resloc.experiments.output import atomic_output_dir, check_output_dir, signals_as_exceptions

    kw = {k: v for k, v in kw.items() if v is not None}
    config = make_config(**kw)  # every flag validated before any work
    if out is None:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        out = Path("runs") / f"mrclam-{Path(path).name}-{stamp}"
    check_output_dir(out, overwrite, [path])  # before any work: a bad --out loses nothing
    data = path
    if NoiseChoice(noise) is NoiseChoice.AUTO:
        data = load_mrclam(path, duration=config.duration, strict=config.strict)
        fitted = noise_from_fit(estimate_noise(data))
        for name, value in fitted.items():
            kw.setdefault(name, value)  # an explicit option wins over the fit
        used = {k: kw[k] for k in fitted}
        print(
            "noise fitted against ground truth: "
            + ", ".join(f"{k} {_fmt_value(v)}" for k, v in used.items())
        )
        config = make_config(**kw)
    if paper_detector:  # an explicit --rho still wins
        config = dataclasses.replace(config.paper_detector(), rho=kw.get("rho", 1.0))
    if plots:
        from resloc.experiments.plots import pyplot

        pyplot()  # fail early if matplotlib is missing
    with signals_as_exceptions(), step_progress(progress) as bar:
        tasks: dict[str, int] = {}

        def report(name: str, k: int, n: int) -> None:
            if name not in tasks:
                label = "dead reckoning" if name == "dr" else name.upper()
                tasks[name] = bar.add_task(label, total=n)
            bar.update(tasks[name], completed=k)

        result = run_mrclam(data, config, progress=report)
    print_mrclam_summary(result)
    with atomic_output_dir(out, overwrite, [path]) as tmp:
        save_mrclam(result, tmp, plots=plots)
    write_exports(out, export)  # after the rename: a failed export keeps the run
    print(f"results written to {out}/ (summary.json, per_robot.csv, timeseries.csv, plots)")
    return result


def register(app: typer.Typer) -> None:
    """Add the ``mrclam`` command to ``app``."""

    @app.command("mrclam")
    @handle_errors
    def mrclam(
        path: Path = typer.Argument(
            ..., help="An MRCLAM dataset folder in the official format (MRCLAM_Dataset1..9)."
        ),
        filter: FilterChoice = typer.Option(
            FilterChoice.ALL, "--filter", "-f", help="Which filter(s) to run."
        ),
        landmarks: bool = typer.Option(
            True, "--landmarks/--no-landmarks", help="Fuse landmark sightings as anchors."
        ),
        zones: bool = typer.Option(
            False, "--zones/--no-zones", help="Adversarial SDZ/CDZ in the arena."
        ),
        sdz: tuple[float, float, float] | None = typer.Option(
            None, "--sdz", help="SDZ disc X Y RADIUS (m) [default: placed automatically]."
        ),
        cdz: tuple[float, float, float] | None = typer.Option(
            None, "--cdz", help="CDZ disc X Y RADIUS (m) [default: placed automatically]."
        ),
        duration: float | None = typer.Option(
            None, "--duration", help="Replay only the first S seconds [default: all]."
        ),
        dt: float = typer.Option(0.02, "--dt", help="Replay step (s), 0.001 to 1."),
        seed: int = typer.Option(
            0, "--seed", "-s", min=0, max=INT64_MAX, help="Seed of attacks and jamming."
        ),
        strict: bool = typer.Option(
            False,
            "--strict",
            help="Fail on any data row that is out of order, repeated, conflicting or "
            "unusable (default: count and report them).",
        ),
        rho: float | None = typer.Option(
            None,
            "--rho",
            help="Attack-detector threshold [default: the chi-square gate at false-alarm "
            "probability 1e-3 with the nis norm, 1.0 with a raw norm].",
        ),
        detector_norm: InnovationNorm = typer.Option(
            InnovationNorm.NIS, "--detector-norm", help="Norm the detector thresholds."
        ),
        detector: bool = typer.Option(True, "--detector/--no-detector", help="Attack detector."),
        recovery: bool = typer.Option(
            True,
            "--recovery/--no-recovery",
            help="Re-admit a robot's sightings after a run of rejections (no lock-out).",
        ),
        recovery_after: int = typer.Option(
            10, "--recovery-after", min=1, help="Consecutive rejections before recovery."
        ),
        paper_detector: bool = typer.Option(
            False,
            "--paper-detector",
            help="The paper's detector: raw euclidean norm, rho 1.0, no recovery.",
        ),
        trigger: bool = typer.Option(
            True, "--trigger/--no-trigger", help="Event trigger (off: transmit every link)."
        ),
        noise: NoiseChoice = typer.Option(
            NoiseChoice.DEFAULT,
            "--noise",
            help="Noise model: default (fitted on Dataset 6) or auto (fitted on this dataset "
            "against its ground truth, as --estimate-noise prints; explicit noise options win).",
        ),
        range_std: float | None = typer.Option(
            None, "--range-std", help="Range noise floor (m) [default: 0.03]."
        ),
        range_std_rel: float | None = typer.Option(
            None, "--range-std-rel", help="Range noise per metre of range [default: 0.07]."
        ),
        bearing_std: float | None = typer.Option(
            None, "--bearing-std", help="Bearing noise (rad) [default: 0.015]."
        ),
        attack_bias: tuple[float, float] = typer.Option(
            (0.4, 0.8), "--attack-bias", help="Injection bound: RANGE (m) BEARING (rad)."
        ),
        out: Path | None = typer.Option(
            None, "--out", "-o", help="Output directory [default: runs/mrclam-<name>-<time>]."
        ),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace a non-empty --out."),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG figures."),
        progress: bool = typer.Option(
            True, "--progress/--no-progress", help="Show progress bars on stderr."
        ),
        estimate_noise: bool = typer.Option(
            False,
            "--estimate-noise",
            help="Only print the sensor noise measured against ground truth, then exit.",
        ),
        export: str | None = export_option(),
    ) -> None:
        """Cooperative localization on a real MRCLAM dataset, scored against ground truth."""
        if estimate_noise:
            noise_command(path, duration, strict)
            return
        filters = ("ckf", "ukf", "ekf") if filter is FilterChoice.ALL else (filter.value,)
        mrclam_command(
            path,
            out,
            overwrite,
            plots,
            progress and sys.stderr.isatty(),
            export,
            noise=noise,
            paper_detector=paper_detector,
            filters=filters,
            dt=dt,
            duration=duration,
            landmarks=landmarks,
            zones=zones,
            sdz=sdz,
            cdz=cdz,
            seed=seed,
            rho=rho,
            detector_norm=detector_norm,
            detector=detector,
            recovery=recovery,
            recovery_after=recovery_after,
            trigger=trigger,
            range_std=range_std,
            range_std_rel=range_std_rel,
            bearing_std=bearing_std,
            attack_bias=attack_bias,
            strict=strict,
        )
