"""Study: the package's defaults on public measurements, against the classical answer (issue 41, item 1).

Seven public data sets with the model a scientist would write (:mod:`torchmisspec.datasets`). Protocols: several
experiments -> leave one experiment out (the held-out experiment predicted from its first row); one trajectory ->
rolling origins (fit on the data up to the origin, forecast the next 3 times). Methods: the package's defaults
(``fit_correction(train, system)``, then ``CorrectedODE(system, gp).predict``; ``posterior(..., num_samples=64)``
with the fitted measurement noise, ``.measured(gp.noise_, gp.noise_scale_)``, for the 90 % band of new
measurements), and the classical answer (the model's uncertain parameters, and the initial states the data
do not give, fitted alone with F = 0 by least squares on log values: :mod:`torchmisspec.paper.real_data`), and
SINDy where every state is measured (the classical parameters, then pysindy's STLSQ on a degree-2 polynomial library
fitted to central-difference samples of F = dy/dt - G(y), G + F integrated; :func:`~real_data.run_sindy`).

Metrics per fold: the log-RMSE of the held-out measurements (``log(1 + y)`` for counts), the default's / the
classical's (geometric mean over folds per data set), whether the held-out measurements lie in the 90 % band,
the wall times, and every exception with its type and message. Each fold runs in a child process with a time
limit per method (the classical answer and the defaults each in their own); a method that passes it is recorded as
an exception of type ``Timeout`` at the stage it was in.
"""

from __future__ import annotations

import math
import multiprocessing
import queue as queue_module
import statistics
import time

from torchmisspec import datasets
from torchmisspec.benchmarks.reporting import ROOT, machine, update_benchmarks, write_json, write_page

from . import real_data

DEFAULT_JSON = ROOT / "benchmarks" / "study_real_data.json"
DOC_PAGE = ROOT / "docs" / "studies" / "real-data-suite.md"

#: Each data set's protocol: the experiments left out (default: all), or the origins (index of the last training
#: time), the forecast horizon and the training window (the last ``window`` times; default all before the origin).
PROTOCOLS = {
    "orange": {},
    "loblolly": {},
    "chickweight": {"experiments": list(range(0, 50, 5))},  # chicks 1, 6, ..., 46: 10 of the 50 folds
    "theoph": {},
    "lynx": {"origins": [79, 87, 95, 103], "horizon": 3, "window": 30},  # 1900, 1908, 1916, 1924
    "hare_lynx": {"origins": [9, 11, 13, 15, 17], "horizon": 3},  # 1909, ..., 1917
    "influenza": {"origins": [6, 7, 8, 9, 10, 11], "horizon": 3},  # days 0-6, ..., 0-11
}
FULL = {"datasets": list(PROTOCOLS), "limit": None, "num_samples": 64, "timeout": 300}
SMOKE = {"datasets": ["orange", "hare_lynx"], "limit": 1, "num_samples": 16, "timeout": 240}
#: The issue's floors, per data set.
GOALS = {"ratio": 1.05, "coverage": (0.80, 0.95), "seconds": 20.0}


def _child(name: str, index: int, method: str, cfg: dict, out) -> None:
    """One method on one fold in a child process, each stage's results put on ``out``."""
    import torch

    torch.set_num_threads(1)
    data = datasets.load(name)
    fold = real_data.folds(data, PROTOCOLS[name])[index]

    def send(**values) -> None:
        out.put(values)

    if method == "classical":
        real_data.run_classical(data, fold, send)
    elif method == "sindy":
        real_data.run_sindy(data, fold, send)
    else:
        real_data.run_default(data, fold, cfg["num_samples"], send)
    out.put({"done": True})


def _stage(record: dict, method: str) -> str:
    """The stage a method that ran out of time was in."""
    if method in ("classical", "sindy"):
        return f"{method} fit"
    for key, stage in (
        ("fit_seconds", "fit_correction"),
        ("default_log_rmse", "predict"),
        ("band_seconds", "posterior"),
    ):
        if key not in record:
            return stage
    return "after the band"


def _run_method(name: str, index: int, method: str, cfg: dict, record: dict) -> None:
    """One method on one fold in a child process with a time limit (``cfg["timeout"]`` seconds): what it sent
    before it ended goes into ``record``; a limit passed or a child that died is recorded as an exception."""
    ctx = multiprocessing.get_context("spawn")
    out = ctx.Queue()
    proc = ctx.Process(target=_child, args=(name, index, method, cfg, out), daemon=True)
    t0 = time.perf_counter()
    proc.start()
    done = False
    while not done and time.perf_counter() - t0 < cfg["timeout"]:
        try:
            values = out.get(timeout=1.0)
        except queue_module.Empty:
            if not proc.is_alive() and out.empty():
                break
            continue
        record["exceptions"] += values.pop("exceptions", [])
        done = bool(values.pop("done", False))
        record.update(values)
    if not done:
        alive = proc.is_alive()
        if alive:
            proc.terminate()
        kind = "Timeout" if alive else "ChildDied"
        message = f"no result within {cfg['timeout']} s" if alive else f"the process ended (exit code {proc.exitcode})"
        record["exceptions"].append({"stage": _stage(record, method), "type": kind, "message": message, "where": ""})
    proc.join(5)


def run_fold(name: str, index: int, label: str, cfg: dict) -> dict:
    """One fold: the classical answer, then the package's defaults, each in its own child with its own limit."""
    record: dict = {"label": label, "exceptions": []}
    t0 = time.perf_counter()
    for method in ("classical", "default", "sindy"):
        _run_method(name, index, method, cfg, record)
    record["wall_seconds"] = time.perf_counter() - t0
    return record


def study(cfg: dict, log=print, workers: int = 1) -> dict:
    """Every fold of every data set (``workers`` folds at a time, each method in its own one-thread child)."""
    from concurrent.futures import ThreadPoolExecutor

    tasks, about = [], {}
    for name in cfg["datasets"]:
        data = datasets.load(name)
        labels = [f["label"] for f in real_data.folds(data, PROTOCOLS[name], cfg["limit"])]
        about[name] = {"citation": data.citation, "description": data.description, "noise": data.noise}
        tasks += [(name, i, label) for i, label in enumerate(labels)]

    def one(task):
        rec = run_fold(*task, cfg)
        log(f"{task[0]} {task[2]}: {_line(rec)}")
        return rec

    with ThreadPoolExecutor(max_workers=workers) as pool:  # the threads only wait on their child processes
        records = list(pool.map(one, tasks))
    runs = {name: [r for (n, _, _), r in zip(tasks, records, strict=True) if n == name] for name in cfg["datasets"]}
    return {"config": cfg, "protocols": PROTOCOLS, "goals": GOALS, "datasets": about, "runs": runs}


def _fmt(x, spec: str = ".3f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _line(rec: dict) -> str:
    errors = "; ".join(f"{e['stage']}: {e['type']}" for e in rec["exceptions"]) or "none"
    return (
        f"default {_fmt(rec.get('default_log_rmse'))}, classical {_fmt(rec.get('classical_log_rmse'))}, "
        f"covered {rec.get('covered', '-')}/{rec.get('scored', '-')}, fit {_fmt(rec.get('fit_seconds'), '.1f')} s, "
        f"band {_fmt(rec.get('band_seconds'), '.1f')} s; exceptions: {errors}"
    )


def summary(runs: list[dict]) -> dict:
    """Per data set: the geometric mean of default / classical over the folds both scored, wins, pooled coverage,
    times and the number of exceptions."""
    pairs = [
        (r["default_log_rmse"], r["classical_log_rmse"])
        for r in runs
        if all(isinstance(r.get(k), float) and math.isfinite(r[k]) for k in ("default_log_rmse", "classical_log_rmse"))
    ]
    logs = [math.log(d / c) for d, c in pairs if d > 0 and c > 0]
    scored = sum(r.get("scored", 0) for r in runs)
    fits = [r["fit_seconds"] for r in runs if "fit_seconds" in r]
    bands = [r["band_seconds"] for r in runs if "band_seconds" in r]
    both = [r["fit_seconds"] + r["band_seconds"] for r in runs if "fit_seconds" in r and "band_seconds" in r]
    return {
        "folds": len(runs),
        "scored_pairs": len(logs),
        "ratio": math.exp(sum(logs) / len(logs)) if logs else float("nan"),
        "wins": sum(d < c for d, c in pairs),
        "coverage": sum(r.get("covered", 0) for r in runs) / scored if scored else float("nan"),
        "band_points": scored,
        "fit_median": statistics.median(fits) if fits else float("nan"),
        "band_median": statistics.median(bands) if bands else float("nan"),
        "fit_band_max": max(both) if both else float("nan"),
        "exceptions": sum(len(r["exceptions"]) for r in runs),
        "folds_with_exceptions": sum(bool(r["exceptions"]) for r in runs),
        **_sindy_summary(runs),
    }


def _sindy_summary(runs: list[dict]) -> dict:
    """SINDy against the classical answer where it applies: the geometric mean of their ratio over the folds both
    scored, and the folds where it applied but gave no finite forecast (its solve failed or blew up)."""
    applies = [r for r in runs if r.get("sindy_applies")]
    pairs = [
        (r["sindy_log_rmse"], r["classical_log_rmse"])
        for r in applies
        if all(
            isinstance(r.get(k), float) and math.isfinite(r[k]) and r[k] > 0
            for k in ("sindy_log_rmse", "classical_log_rmse")
        )
    ]
    logs = [math.log(s / c) for s, c in pairs]
    return {
        "sindy_folds": len(applies),
        "sindy_ratio": math.exp(sum(logs) / len(logs)) if logs else float("nan"),
        "sindy_scored": len(logs),
        "sindy_failed": sum(not math.isfinite(r.get("sindy_log_rmse", math.nan)) for r in applies),
    }


def _sindy_cell(s: dict) -> str:
    if not s["sindy_folds"]:
        return "does not apply"
    return f"{_fmt(s['sindy_ratio'])} ({s['sindy_scored']} scored, {s['sindy_failed']} failed)"


def table(result: dict) -> str:
    lines = [
        "| data set | folds | default / classical log-RMSE (geometric mean) | default better | 90 % band coverage "
        "(points) | fit s (median) | band s (median) | fit + band s (max) | exceptions (folds) | SINDy / classical "
        "(geometric mean) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, runs in result["runs"].items():
        s = summary(runs)
        lines.append(
            f"| {name} | {s['folds']} | {_fmt(s['ratio'])} ({s['scored_pairs']} scored) | {s['wins']} of "
            f"{s['scored_pairs']} | {_fmt(s['coverage'], '.2f')} ({s['band_points']}) | {_fmt(s['fit_median'], '.1f')} "
            f"| {_fmt(s['band_median'], '.1f')} | {_fmt(s['fit_band_max'], '.1f')} | {s['exceptions']} "
            f"({s['folds_with_exceptions']}) | {_sindy_cell(s)} |"
        )
    return "\n".join(lines) + "\n"


def per_fold(result: dict) -> str:
    lines = [
        "| data set | fold | default log-RMSE | classical log-RMSE | ratio | in band | fit s | band s | classical s "
        "| kernel | exceptions | SINDy log-RMSE |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, runs in result["runs"].items():
        for r in runs:
            d, c = r.get("default_log_rmse"), r.get("classical_log_rmse")
            ratio = d / c if isinstance(d, float) and isinstance(c, float) and c > 0 else None
            errors = "; ".join(f"{e['stage']}: {e['type']}" for e in r["exceptions"]) or "none"
            lines.append(
                f"| {name} | {r['label']} | {_fmt(d)} | {_fmt(c)} | {_fmt(ratio, '.2f')} | "
                f"{r.get('covered', '-')}/{r.get('scored', '-')} | {_fmt(r.get('fit_seconds'), '.1f')} | "
                f"{_fmt(r.get('band_seconds'), '.1f')} | {_fmt(r.get('classical_seconds'), '.1f')} | "
                f"{r.get('kernel', '-')} | {errors} | "
                + ("n/a" if not r.get("sindy_applies") else _fmt(r.get("sindy_log_rmse")))
                + " |"
            )
    return "\n".join(lines) + "\n"


def exceptions(result: dict) -> str:
    lines = []
    for name, runs in result["runs"].items():
        for r in runs:
            for e in r["exceptions"]:
                message = " ".join(e["message"].split()).replace("|", "/")
                lines.append(f"- **{name}, {r['label']}**, {e['stage']}: `{e['type']}` ({e['where']}): {message}")
    return "\n".join(lines) + "\n" if lines else "None.\n"


def goals(result: dict) -> str:
    rows, better = [], 0
    lo, hi = GOALS["coverage"]
    for name, runs in result["runs"].items():
        s = summary(runs)
        better += s["ratio"] < 1.0
        rows.append(
            f"- {name}: zero exceptions **{'PASS' if s['exceptions'] == 0 else 'FAIL'}** ({s['exceptions']}); "
            f"ratio <= {GOALS['ratio']} **{'PASS' if s['ratio'] <= GOALS['ratio'] else 'FAIL'}** ({_fmt(s['ratio'])}); "
            f"coverage in [{lo}, {hi}] **{'PASS' if lo <= s['coverage'] <= hi else 'FAIL'}** "
            f"({_fmt(s['coverage'], '.2f')}); fit + band <= {GOALS['seconds']:g} s "
            f"**{'PASS' if s['fit_band_max'] <= GOALS['seconds'] else 'FAIL'}** ({_fmt(s['fit_band_max'], '.1f')} s)"
        )
    n = len(result["runs"])
    rows.append(
        f"- default better (ratio < 1) on at least half: **{'PASS' if 2 * better >= n else 'FAIL'}** ({better} of {n})"
    )
    return "\n".join(rows) + "\n"


def render_page(result: dict, wall: float, command: str) -> str:
    info = result["machine"]
    sets = "\n".join(
        f"- **{name}**: {a['description']} ({'log(1 + y)' if a['noise'] == 'counts' else 'log y'}; protocol "
        f"`{result['protocols'][name] or 'leave one experiment out, every experiment'}`). Source: {a['citation']}."
        for name, a in result["datasets"].items()
    )
    return f"""# Study: the real-data suite

This page is written by `{command}`; every number on it comes from that run (raw numbers:
`benchmarks/study_real_data.json`). Machine: {info["cpu"]}, {info["logical_cpus"]} logical CPUs, torch
{info["torch"]} ({info["torch_threads"]} threads in the parent; each method of each fold in a child process with
1 thread), commit {info["git_commit"]} (library modified: {info["library_modified"]}); wall time {wall / 60:.1f} min;
each method limited to {result["config"]["timeout"]} s per fold.

{__doc__.strip()}

## Data sets and models

{sets}

Data and models: `torchmisspec.datasets` (CSV files, sources and licences in `torchmisspec/datasets/data/`).

## Goals (issue 41's floors)

{goals(result)}
## Per data set

{table(result)}
## Per fold

Log-RMSE of the held-out measurements; "in band": held-out measurements inside the default's 90 % band of new
measurements (of those scored).

{per_fold(result)}
## Exceptions

{exceptions(result)}"""


MARK_START, MARK_END = "<!-- study:real-data:start -->", "<!-- study:real-data:end -->"


def render_block(result: dict, wall: float, command: str) -> str:
    """The study's section of BENCHMARKS.md: the per-data-set table and the goals."""
    info = result["machine"]
    return f"""{MARK_START}
## The real-data suite (`scripts/study_real_data.py`)

Written by `{command}` ({wall / 60:.1f} min, {info["cpu"]}, {info["logical_cpus"]} logical CPUs, commit
{info["git_commit"]}): seven public data sets, the package's defaults against the classical answer (the model's
parameters and unknown initial states fitted alone, F = 0, on log values), per fold; see
[docs/studies/real-data-suite.md](docs/studies/real-data-suite.md).

{table(result)}
{goals(result)}{MARK_END}
"""


def run(args) -> int:
    """The command line's run: the study (or ``--from-json``), its JSON, its table; ``--markdown`` writes the page
    and the block of BENCHMARKS.md."""
    import sys

    if args.saved is not None:
        result, wall = args.saved, args.saved["wall_seconds"]
    else:
        cfg = SMOKE if args.smoke else FULL
        t0 = time.perf_counter()
        result = study(cfg, workers=args.workers or 1)
        wall = time.perf_counter() - t0
        result.update(machine=machine(), wall_seconds=wall, smoke=args.smoke, command=" ".join(["python", *sys.argv]))
        write_json(result, real_data_json(args))
    print(table(result))
    if args.markdown:
        command = result.get("command", "python scripts/study_real_data.py")
        write_page(DOC_PAGE, render_page(result, wall, command))
        update_benchmarks(render_block(result, wall, command), MARK_START, MARK_END)
        print(f"wrote {DOC_PAGE} and the block of BENCHMARKS.md")
    return 0


def real_data_json(args):
    from torchmisspec.benchmarks.reporting import run_json

    return run_json(args, DEFAULT_JSON)
