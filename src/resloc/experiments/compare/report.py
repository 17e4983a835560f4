"""What ``resloc compare`` reports: the result object, its rows, the targets, the Markdown
section and the files (``compare.json``, ``compare.md``, ``roc.csv``, ``lambda2.csv``,
``roc.png``)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from resloc.experiments.compare.methods import BEST, NAIVE_REFERENCE, PAPER
from resloc.experiments.metrics import nees_band
from resloc.experiments.stats import mean_ci, ratio

__all__ = ["CompareResult", "compare_result", "nees_band", "save_compare"]


def _est(samples) -> dict:
    e = mean_ci(samples)
    return {"mean": e.mean, "ci": e.half, "n": e.n}


@dataclass
class CompareResult:
    """Everything ``resloc compare`` measured (plain, JSON-ready data).

    Attributes
    ----------
    config : dict
        seeds, steps, filter, quick, jobs, wall time.
    table : list of dict
        Main table rows: scenario, method, metric -> {mean, ci, n}.
    fusion : list of dict
        Fusion-consistency rows on the default scenario.
    roc : list of dict
        One row per gate, attack and threshold: TPR / FPR with intervals.
    lambda2 : list of dict
        One row per team size and lambda2 mode.
    targets : list of dict
        The issue's targets with the measured values and whether they are met.
    """

    config: dict
    table: list[dict]
    fusion: list[dict]
    roc: list[dict]
    lambda2: list[dict]
    targets: list[dict]

    def to_dict(self) -> dict:
        """Plain mapping for JSON."""
        return dataclasses.asdict(self)

    def markdown(self) -> str:
        """The report section (Markdown)."""
        return _markdown(self)


def compare_result(config: dict, outputs: list[dict]) -> CompareResult:
    """The result of the study's cells ``outputs`` (each ``{"task": ..., "metrics": ...}``,
    in task order) run with ``config``."""
    seeds = config["seeds"]
    table = [_table_row(o) for o in outputs if o["task"]["study"] in ("table", "extra")]
    fusion = [_fusion_row(o, seeds) for o in outputs if o["task"]["study"] == "fusion"]
    roc = [row for o in outputs if o["task"]["study"] == "roc" for row in _roc_rows(o)]
    lam = [_lambda2_row(o) for o in outputs if o["task"]["study"] == "lambda2"]
    raw = {o["task"]["label"]: o["metrics"] for o in outputs}
    return CompareResult(config, table, fusion, roc, lam, _targets(fusion, raw))


#: The per-trial metrics of a cell summarized as mean and interval.
_SUMMARIZED = (
    "msle msle_final rmse nees nees_rel comm_rate bytes_per_step tpr fpr attacked_fused"
).split()


def _summarize_cell(out: dict) -> dict:
    m = out["metrics"]
    summary = {key: _est(m.get(key, [float("nan")])) for key in _SUMMARIZED}
    return {**summary, "repairs": m["repairs"], "wall_time_s": m["wall_time_s"]}


def _table_row(o: dict) -> dict:
    t = o["task"]
    return {
        "study": t["study"],
        "scenario": t["scenario_key"],
        "scenario_label": t["scenario_label"],
        "method": t["method_key"],
        "method_label": t["method_label"],
        **_summarize_cell(o),
    }


def _fusion_row(o: dict, seeds: int) -> dict:
    t, m = o["task"], o["metrics"]
    # M = seeds: with relative measurements only the team's absolute pose is unobservable,
    # so all robots of a trial share one common error and their NEES are not
    # independent; the trials are (docs/beyond.md).
    lo, hi = nees_band(3, seeds)
    lo1, hi1 = nees_band(3, 1)
    per_seed = np.asarray(m["nees"], float)
    return {
        "method": t["method_key"],
        "method_label": t["method_label"],
        **_summarize_cell(o),
        "nees_band": [lo, hi],
        "nees_per_seed": per_seed.tolist(),
        "nees_seeds_in_band": float(np.mean((per_seed >= lo1) & (per_seed <= hi1))),
    }


def _roc_rows(o: dict) -> list[dict]:
    t, m = o["task"], o["metrics"]
    seeds = t["seeds"]
    rows = []
    for k, value in enumerate(t["values"]):
        sl = slice(k * seeds, (k + 1) * seeds)
        rows.append(
            {
                "attack": t["scenario_key"],
                "gate": t["method_key"],
                "threshold": value,
                "threshold_name": t["threshold_name"],
                "tpr": _est(np.asarray(m["tpr"])[sl]),
                "fpr": _est(np.asarray(m["fpr"])[sl]),
                "msle": _est(np.asarray(m["msle"])[sl]),
            }
        )
    return rows


def _lambda2_row(o: dict) -> dict:
    t, m = o["task"], o["metrics"]
    row = {
        "robots": t["robots"],
        "mode": t["method_key"],
        "comm_rate": _est(m["comm_rate"]),
        "msle": _est(m["msle"]),
    }
    if "lambda2" in o:
        row["lambda2_true_mean"] = o["lambda2"]["true_mean"]
        if "estimate_mean" in o["lambda2"]:
            row["lambda2_estimate_mean"] = o["lambda2"]["estimate_mean"]
            row["lambda2_abs_rel_error"] = o["lambda2"]["abs_rel_error_after_warmup"]
    return row


def _targets(fusion: list[dict], raw: dict) -> list[dict]:
    """The issue's quantitative targets, checked on the measurements."""
    out = []
    naive = next((r for r in fusion if r["method"] == NAIVE_REFERENCE), None)
    for r in fusion:
        if "nis" not in r["method"] or naive is None or r["method"] == NAIVE_REFERENCE:
            continue
        lo, hi = r["nees_band"]
        nees = r["nees"]["mean"]
        fac = r["msle"]["mean"] / naive["msle"]["mean"]
        out.append(
            {
                "target": (
                    f"fusion {r['method']}: NEES in band, MSLE <= 2x {NAIVE_REFERENCE} "
                    "(default scenario)"
                ),
                "measured": f"NEES {nees:.3g} (band {lo:.2f}-{hi:.2f}), MSLE x{fac:.3g}",
                "met": bool(lo <= nees <= hi and fac <= 2.0),
            }
        )
    for method in (BEST, PAPER):
        a = raw.get(f"table: sdz_stealthy / {method}")
        b = raw.get(f"table: clean / {method}")
        if a is None or b is None:
            continue
        est = ratio(a["msle"], b["msle"])
        fac = float(np.nanmean(a["msle"]) / np.nanmean(b["msle"]))
        met = fac <= 3.0 if method == BEST else fac > 3.0
        out.append(
            {
                "target": (
                    f"stealthy: {method} MSLE within 3x of its clean run"
                    if method == BEST
                    else "stealthy: the paper's configuration far worse than 3x of its clean run"
                ),
                # The world's stealthy attacker stops at 0.9 of each test (it holds back):
                # the row says so, so that nobody reads it as a resilience result.
                "measured": (
                    f"ratio of means x{fac:.3g} (per-seed ratio {est.format('.3g')}); "
                    "against the world's stealthy attacker, which holds back (0.9 of each "
                    "test): not a resilience result, see `resloc attack`"
                ),
                "met": bool(met),
            }
        )
    return out


# ---------------------------------------------------------------------------- output
def _fmt(e: dict, spec: str = ".3g") -> str:
    mean, half = e.get("mean"), e.get("ci")
    if mean is None or not math.isfinite(mean):
        return "-"
    if half is None or not math.isfinite(half):
        return f"{mean:{spec}}"
    return f"{mean:{spec}} ± {half:{spec}}"


def _markdown(res: CompareResult) -> str:
    c = res.config
    lines = [
        "## Beyond the paper: consistent fusion, unit-aware detection, stealthy attackers, "
        "local lambda2",
        "",
        f"`resloc compare{' --quick' if c['quick'] else ''}`: {c['robots']} robots "
        f"(arc-turn), filter {c['filter'].upper()}, {c['seeds']} seeds per cell, "
        f"{c['steps']} steps; means ± 95% Student-t half-widths over seeds; "
        f"{c['cells']} runs in {c['wall_time_s']:.0f} s with {c['jobs']} job(s). "
        "Methods and references: `docs/beyond.md`.",
        "",
    ]
    if c["quick"]:
        lines += [
            "*--quick is a smoke test (zones moved onto the first 200 steps, while the filters "
            "are still converging): its numbers and target checks are not the study's.*",
            "",
        ]
    if res.table:
        lines += [
            "### Method x scenario",
            "",
            "NEES rel.: the relative error's NEES (the team's least-squares rigid-body error "
            "removed). Bytes/step: every robot-to-robot frame (estimates, acknowledgements, "
            "consensus) at the runtime's wire sizes; '-' where a method's traffic is not "
            "counted (tracked is centralized; factorized's factor messages are not counted).",
            "",
            "| scenario | method | MSLE | RMSE (m) | NEES | NEES rel. | comm. rate | bytes/step "
            "| TPR | FPR |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in res.table:
            lines.append(
                f"| {r['scenario_label']} | {r['method_label']} | {_fmt(r['msle'])} | "
                f"{_fmt(r['rmse'])} | {_fmt(r['nees'])} | {_fmt(r['nees_rel'])} | "
                f"{_fmt(r['comm_rate'], '.3f')} | {_fmt(r['bytes_per_step'], '.4g')} | "
                f"{_fmt(r['tpr'], '.3f')} | {_fmt(r['fpr'], '.3f')} |"
            )
        lines.append("")
    if res.fusion:
        lo, hi = res.fusion[0]["nees_band"]
        lines += [
            "### Fusion consistency (default scenario: SDZ random injections + CDZ)",
            "",
            f"NEES: the time-and-robot average of each seed, then the mean over seeds; the "
            f"95% chi-square band of a mean of {c['seeds']} independent 3-DoF NEES is "
            f"{lo:.2f}-{hi:.2f} (the robots of one trial share the team's unobservable "
            "absolute error, so the seeds are the independent samples). 'seeds in band': the "
            "share of seeds inside the single-trial band (0.22-9.35).",
            "",
            f"'MSLE / naive': against naive fusion with the same detector ({NAIVE_REFERENCE}).",
            "",
            "| fusion, detector | NEES | seeds in band | MSLE | MSLE / naive | RMSE (m) | "
            "comm. rate |",
            "|---|---|---|---|---|---|---|",
        ]
        ref = next((r for r in res.fusion if r["method"] == NAIVE_REFERENCE), res.fusion[0])
        naive = ref["msle"]["mean"]
        for r in res.fusion:
            lines.append(
                f"| {r['method_label']} | {_fmt(r['nees'])} | {r['nees_seeds_in_band']:.0%} | "
                f"{_fmt(r['msle'])} | {r['msle']['mean'] / naive:.3g} | {_fmt(r['rmse'])} | "
                f"{_fmt(r['comm_rate'], '.3f')} |"
            )
        lines.append("")
    if res.roc:
        lines += [
            "### Detector ROC (closed loop, gauge fusion; each threshold its own trials)",
            "",
            "| attack | gate | threshold | TPR | FPR | MSLE |",
            "|---|---|---|---|---|---|",
        ]
        for r in res.roc:
            lines.append(
                f"| {r['attack']} | {r['gate']} | {r['threshold_name']} = {r['threshold']:g} | "
                f"{_fmt(r['tpr'], '.3f')} | {_fmt(r['fpr'], '.4f')} | {_fmt(r['msle'])} |"
            )
        lines.append("")
    if res.lambda2:
        lines += [
            "### lambda2 and the trigger with team size (clean, paper's method)",
            "",
            "| N | lambda2 | true lambda2 (mean) | estimate error (mean abs. rel.) | "
            "comm. rate | MSLE |",
            "|---|---|---|---|---|---|",
        ]
        for r in res.lambda2:
            true = r.get("lambda2_true_mean")
            err = r.get("lambda2_abs_rel_error")
            lines.append(
                f"| {r['robots']} | {r['mode']} | {'-' if true is None else f'{true:.3g}'} | "
                f"{'-' if err is None else f'{err:.1%}'} | {_fmt(r['comm_rate'], '.3f')} | "
                f"{_fmt(r['msle'])} |"
            )
        lines.append("")
    if res.targets:
        lines += ["### Targets", "", "| target | measured | met |", "|---|---|---|"]
        for t in res.targets:
            lines.append(f"| {t['target']} | {t['measured']} | {'yes' if t['met'] else 'no'} |")
        lines.append("")
    return "\n".join(lines)


def save_compare(result: CompareResult, out: Path, plots: bool = True) -> list[Path]:
    """Write ``compare.json``, ``compare.md`` (the report section), ``roc.csv``,
    ``lambda2.csv`` and, with matplotlib and ``plots``, ``roc.png``."""
    from resloc.experiments.run_files import write_json

    out = Path(out)
    written = []
    p = out / "compare.json"
    write_json(p, result.to_dict())
    written.append(p)
    p = out / "compare.md"
    p.write_text(result.markdown() + "\n", encoding="utf-8")
    written.append(p)
    nan = float("nan")
    tables = {
        "roc.csv": (
            "attack,gate,threshold_name,threshold,tpr,fpr,msle",
            (
                f"{r['attack']},{r['gate']},{r['threshold_name']},{r['threshold']:g},"
                f"{r['tpr']['mean']:.6g},{r['fpr']['mean']:.6g},{r['msle']['mean']:.6g}"
                for r in result.roc
            ),
        ),
        "lambda2.csv": (
            "robots,mode,comm_rate,lambda2_true_mean,lambda2_abs_rel_error",
            (
                f"{r['robots']},{r['mode']},{r['comm_rate']['mean']:.6g},"
                f"{r.get('lambda2_true_mean', nan):.6g},{r.get('lambda2_abs_rel_error', nan):.6g}"
                for r in result.lambda2
            ),
        ),
    }
    for name, (header, rows) in tables.items():
        p = out / name
        p.write_text("".join(f"{line}\n" for line in (header, *rows)), encoding="utf-8")
        written.append(p)
    if plots and result.roc:
        from resloc.errors import ConfigError
        from resloc.experiments.plots.compare import plot_roc

        try:
            written.append(plot_roc(result.roc, out / "roc.png"))
        except ConfigError:  # matplotlib missing: the CSV holds the curves
            pass
    return written
