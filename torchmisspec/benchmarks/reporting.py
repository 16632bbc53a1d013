"""What the benchmarks and the studies record and write, one copy for all of them: the machine and the code they ran
on, their command lines, median timings, raw results as JSON, and their markdown blocks between markers in
BENCHMARKS.md (each script keeps its own block there)."""

from __future__ import annotations

import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: The repository the package runs from (the scripts, BENCHMARKS.md, docs/ and benchmarks/ live there).
ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS_MD = ROOT / "BENCHMARKS.md"


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def git(*args: str) -> str | None:
    """Output of ``git args...`` in the repository, or None when git or the repository is not available."""
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def replace_marked(text: str, block: str, start: str, end: str) -> str:
    """``text`` with the block between the markers ``start`` ... ``end`` (markers included) replaced by ``block``,
    or ``block`` appended when the markers are absent (how the scripts keep their sections of BENCHMARKS.md)."""
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end) + r"\n?", re.S)
    if pattern.search(text):
        return pattern.sub(lambda _: block, text, count=1)
    return text.rstrip("\n") + "\n\n" + block


def machine() -> dict:
    """The machine, the library's commit (and whether the library has uncommitted changes) and versions."""
    import torch

    import torchmisspec

    status = git("status", "--porcelain", "--", "torchmisspec")
    return {
        # a copy whose git folder is not its own (a GPU machine's) names its commit in TORCHMISSPEC_COMMIT
        "git_commit": os.environ.get("TORCHMISSPEC_COMMIT") or git("rev-parse", "--short", "HEAD"),
        "library_modified": None if status is None else bool(status),
        "cpu": cpu_model(),
        "logical_cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torchmisspec": torchmisspec.__version__,
    }


def study_arguments(doc: str, argv, default_json: Path, extra=None):
    """The study scripts' command line: ``--smoke``, ``--json``, ``--markdown``, ``--from-json`` (plus what ``extra``
    adds to the parser), checked; ``args.saved`` is the run read from ``--from-json`` (never a smoke run) or None."""
    import argparse

    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes; never writes the docs")
    parser.add_argument("--json", help=f"raw results (default {default_json.relative_to(ROOT)}; smoke: only if given)")
    parser.add_argument("--markdown", action="store_true", help="write the docs page and the BENCHMARKS block")
    parser.add_argument("--from-json", help="render a saved full run (its JSON) instead of running the study")
    parser.add_argument(
        "--workers", type=int, help="run the realizations in a local pool of this many processes (same numbers)"
    )
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    if args.smoke and args.markdown:
        parser.error("--smoke never writes the docs; drop --markdown")
    args.saved = None
    if args.from_json:
        args.saved = json.loads(Path(args.from_json).read_text())
        if args.saved.get("smoke"):
            parser.error("--from-json: that run is a smoke run; its numbers never go into the docs")
    args.parser = parser
    return args


def run_json(args, default_json: Path) -> Path | None:
    """Where a fresh run of a study writes its raw results: ``--json``, else ``default_json`` (a smoke run: only
    where ``--json`` says)."""
    return Path(args.json) if args.json else (None if args.smoke else default_json)


def write_json(result: dict, path: Path | None) -> None:
    """Write a study's raw results to ``path`` (its folder created); nothing when ``path`` is None."""
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=1))


def benchmark_arguments(doc: str, argv, smoke_help: str = "tiny sizes; never writes BENCHMARKS.md", extra=None):
    """The benchmark scripts' command line: ``--smoke``, ``--markdown``, ``--repeats`` (plus what ``extra`` adds to the
    parser), checked; also sets ``args.command`` (how it was run), ``args.load`` (the load average before the run)
    and ``args.parser``."""
    import argparse

    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help=smoke_help)
    parser.add_argument("--markdown", action="store_true", help="write the block of BENCHMARKS.md")
    parser.add_argument("--repeats", type=int, default=3)
    if extra is not None:
        extra(parser)
    args = parser.parse_args(argv)
    if args.smoke and args.markdown:
        parser.error("--smoke never writes BENCHMARKS.md")
    script = Path(sys.argv[0]).name if argv is None else "script"
    args.command = f"python scripts/{script} " + " ".join(sys.argv[1:] if argv is None else argv)
    args.load = " / ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    args.parser = parser
    return args


def run_sentence(args) -> str:
    """How and where a benchmark ran: its command, the machine, the commit and the load average before the run."""
    info = machine()
    return (
        f"Command `{args.command.strip()}`; {info['cpu']}, {info['logical_cpus']} logical CPUs, torch {info['torch']} "
        f"({info['torch_threads']} threads), commit {info['git_commit']}, load average before the run {args.load}."
    )


def update_benchmarks(block: str, start: str, end: str, path: Path | None = None) -> None:
    """Put ``block`` (its markers included) into ``path`` (default BENCHMARKS.md) in place of the old one, or append
    it: how every benchmark and study writes its block."""
    path = BENCHMARKS_MD if path is None else path
    path.write_text(replace_marked(path.read_text() if path.exists() else "", block, start, end))


def publish(lines: list[str], markdown: bool, start: str, end: str) -> None:
    """Print a benchmark's block (``lines`` between the markers) and, with ``markdown``, put it into BENCHMARKS.md."""
    text = "\n".join([start, *lines, end, ""])
    print(text)
    if markdown:
        update_benchmarks(text, start, end)


def write_page(path: Path, text: str) -> None:
    """Write a docs page (its folder created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def timed(fn, repeats: int, setup=None):
    """``(last output, median wall time, every wall time)`` of ``fn()`` over ``repeats`` calls (``setup()`` before
    each, not timed): how every benchmark times."""
    times, out = [], None
    for _ in range(repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times), times


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MB (VmHWM; ru_maxrss can carry the parent's peak across exec)."""
    import resource

    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def memory_gb() -> float | None:
    """Total memory of the machine (GB, from /proc/meminfo), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) / 1024**2
    except OSError:
        pass
    return None


def load_average() -> list[float]:
    """The 1 / 5 / 15 min load average, rounded (empty where the platform has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def version(module: str) -> str | None:
    """``module.__version__``, or None when it is not installed."""
    try:
        return __import__(module).__version__
    except ImportError:
        return None


def run_worker(module: str, payload, threads: int, env: dict | None = None):
    """Run ``python -m module --threads N PAYLOAD`` (a benchmark's worker, in a fresh process so that its memory and
    threads are its own) with this copy of the package first on the path; the JSON of its last output line."""
    package_root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH", "")) if p)
    cmd = [sys.executable, "-m", module, "--threads", str(threads), json.dumps(payload)]
    env = dict(os.environ, **(env or {}), PYTHONPATH=path)
    proc = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def worker_main(work) -> None:
    """The ``__main__`` of a worker module: ``--threads N PAYLOAD`` -> print the JSON of ``work(*PAYLOAD)``."""
    import torch

    threads, payload = int(sys.argv[2]), json.loads(sys.argv[3])
    torch.set_num_threads(threads)
    print(json.dumps(work(*payload)))


def run_study(args, module) -> int:
    """A study's command line run (``args`` from :func:`study_arguments`) for a study ``module`` defining ``study``,
    ``FULL``, ``SMOKE``, ``DEFAULT_JSON``, ``DOC_PAGE``, ``MARK_START``, ``MARK_END``, ``table``, ``render_page`` and
    ``render_block``: the study (or the saved run of ``--from-json``), its JSON, its table printed, and with
    ``--markdown`` the docs page and the study's block of BENCHMARKS.md."""
    import time

    if args.saved is not None:
        result, wall = args.saved, args.saved["wall_seconds"]
        json_path = module.DEFAULT_JSON if args.markdown else None
    else:
        cfg = module.SMOKE if args.smoke else module.FULL
        t0 = time.perf_counter()
        if args.workers is None:
            result = module.study(cfg)
        else:
            import inspect

            from torchmisspec.parallel import process_pool

            if "executor" not in inspect.signature(module.study).parameters:
                args.parser.error("--workers: this study runs its realizations serially (no executor yet)")
            with process_pool(args.workers) as pool:
                result = module.study(cfg, executor=pool)
        wall = time.perf_counter() - t0
        result["machine"], result["wall_seconds"], result["smoke"] = machine(), wall, args.smoke
        result["workers"] = args.workers  # None: serial
        json_path = run_json(args, module.DEFAULT_JSON)
    write_json(result, json_path)
    print(module.table(result))
    if args.markdown:
        write_page(module.DOC_PAGE, module.render_page(result, wall))
        update_benchmarks(module.render_block(result, wall), module.MARK_START, module.MARK_END, BENCHMARKS_MD)
        print(f"wrote {module.DOC_PAGE} and its block of {BENCHMARKS_MD}")
    return 0
