"""The hot paths at two versions of the library, measured in one run: does a change (the input checks of issue 25)
slow prediction or the design?

Both versions run ``scripts/benchmark.py --only predict --only design`` of their own tree (the older one from a
temporary ``git worktree`` of ``--base``), alternating which goes first in each of ``--rounds`` rounds, so that a
change in the machine's load falls on both. Reported for ``CorrectedODE.predict`` (1,000 initial conditions, 61
times) and the lazy greedy (10,000 candidates, K = 50, T = 20, three kernels): the median and the fastest of every
repeat of every round, the ratio this / base of the medians of each round (the two versions ran minutes apart, so
the pairing removes most of the drift of a shared machine) with their geometric mean and range, and whether the
greedy's information gain is the same.

``scripts/benchmark_versions.py`` is its command line.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from .reporting import ROOT, git, publish, run_sentence

MARK_START = "<!-- bench:versions:start -->"
MARK_END = "<!-- bench:versions:end -->"


def _suite(tree: Path, smoke: bool, repeats: int, out: Path) -> dict:
    """``scripts/benchmark.py --only predict --only design`` of the library in ``tree``, its JSON."""
    cmd = [sys.executable, str(tree / "scripts" / "benchmark.py"), "--only", "predict", "--only", "design"]
    cmd += ["--repeats", str(repeats), "--json", str(out)] + (["--smoke"] if smoke else [])
    env = dict(os.environ, PYTHONPATH=str(tree))
    subprocess.run(cmd, check=True, env=env, cwd=tree, capture_output=True, text=True)
    return json.loads(out.read_text())


def _times(result: dict) -> dict[str, list[float]]:
    """Every timed repeat of each measured path of one suite run."""
    times = {"predict": result["predict"]["ours_all_seconds"]}
    for key, row in result["design"].items():
        times[f"greedy {key}"] = row["all_seconds"]
    return times


def _gains(result: dict) -> dict[str, float]:
    return {f"greedy {key}": row["information_gain_nats"] for key, row in result["design"].items()}


def compare(base: str, rounds: int, repeats: int, smoke: bool) -> dict:
    """Run both versions ``rounds`` times, alternating which goes first; every repeat and the greedy's gains."""
    base_commit = git("rev-parse", "--short", base)
    if base_commit is None:
        raise SystemExit(f"--base: expected a revision of this repository, got {base!r}")
    head_commit = git("rev-parse", "--short", "HEAD")
    scratch = Path(tempfile.mkdtemp(prefix="torchmisspec-versions-"))
    worktree = scratch / "base"
    git("worktree", "add", "--detach", str(worktree), base)
    try:
        trees = {"base": worktree, "this": ROOT}
        times = {name: {} for name in trees}
        gains = {}
        for r in range(rounds):
            order = ["base", "this"] if r % 2 == 0 else ["this", "base"]
            for name in order:
                result = _suite(trees[name], smoke, repeats, scratch / f"{name}-{r}.json")
                for path, ts in _times(result).items():
                    times[name].setdefault(path, []).append(ts)  # one list per round
                gains.setdefault(name, _gains(result))
                print(f"round {r + 1}/{rounds}: {name} done", file=sys.stderr)
    finally:
        git("worktree", "remove", "--force", str(worktree))
        shutil.rmtree(scratch, ignore_errors=True)
    return {"base": base_commit, "this": head_commit, "times": times, "gains": gains, "rounds": rounds}


def table(result: dict) -> list[str]:
    """The markdown table: per path, both versions' median and fastest repeat, the paired ratios of the rounds."""
    lines = [
        f"| path | base {result['base']}: median (fastest) | this {result['this']}: median (fastest) | this / base, "
        "rounds paired: geometric mean [range] | repeats each | same information gain |",
        "|---|---|---|---|---|---|",
    ]
    for path, before in result["times"]["base"].items():
        after = result["times"]["this"][path]
        pooled_b, pooled_a = [t for r in before for t in r], [t for r in after for t in r]
        ratios = [statistics.median(a) / statistics.median(b) for a, b in zip(after, before, strict=True)]
        geo = math.exp(statistics.fmean(math.log(x) for x in ratios))
        same = ""
        if path in result["gains"]["base"]:
            same = str(result["gains"]["base"][path] == result["gains"]["this"][path])
        lines.append(
            f"| {path} | {statistics.median(pooled_b) * 1e3:.1f} ms ({min(pooled_b) * 1e3:.1f}) | "
            f"{statistics.median(pooled_a) * 1e3:.1f} ms ({min(pooled_a) * 1e3:.1f}) | **{geo:.2f}** "
            f"[{min(ratios):.2f}, {max(ratios):.2f}] | {len(pooled_b)} | {same} |"
        )
    return lines


def run(args) -> int:
    result = compare(args.base, args.rounds, args.repeats, args.smoke)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    lines = [
        "## The hot paths before and after a change (`scripts/benchmark_versions.py`)",
        "",
        run_sentence(args),
        f"Base: commit {result['base']}; this: commit {result['this']}. Each version runs `scripts/benchmark.py "
        f"--only predict --only design` of its own tree, {result['rounds']} rounds alternating which goes first "
        "(predict: 1,000 initial conditions, 61 times; greedy: 10,000 candidates, K = 50, T = 20, in a fresh "
        "process). Medians and fastest repeats pool every round; the ratio pairs the medians of each round.",
        "",
        *table(result),
    ]
    publish(lines, args.markdown, MARK_START, MARK_END)
    return 0
