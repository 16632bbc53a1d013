"""What the benchmark and study scripts record about the machine and the code they ran on (one shared copy)."""

from __future__ import annotations

import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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
    import re

    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end) + r"\n?", re.S)
    if pattern.search(text):
        return pattern.sub(lambda _: block, text, count=1)
    return text.rstrip("\n") + "\n\n" + block


def machine() -> dict:
    """The machine, the library's commit (and whether the library has uncommitted changes) and versions."""
    import os

    import torch

    import torchmisspec

    status = git("status", "--porcelain", "--", "torchmisspec")
    return {
        "git_commit": git("rev-parse", "--short", "HEAD"),
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
    import json

    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help="tiny sizes; never writes the docs")
    parser.add_argument("--json", help=f"raw results (default {default_json.relative_to(ROOT)}; smoke: only if given)")
    parser.add_argument("--markdown", action="store_true", help="write the docs page and the BENCHMARKS block")
    parser.add_argument("--from-json", help="render a saved full run (its JSON) instead of running the study")
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
    import json

    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=1))


def benchmark_arguments(doc: str, argv, smoke_help: str = "tiny sizes; never writes BENCHMARKS.md"):
    """The benchmark scripts' command line: ``--smoke``, ``--markdown``, ``--repeats`` (checked); also sets
    ``args.command`` (how it was run) and ``args.load`` (the load average before the run)."""
    import argparse
    import os
    import sys

    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--smoke", action="store_true", help=smoke_help)
    parser.add_argument("--markdown", action="store_true", help="write the block of BENCHMARKS.md")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    if args.smoke and args.markdown:
        parser.error("--smoke never writes BENCHMARKS.md")
    script = Path(sys.argv[0]).name if argv is None else "script"
    args.command = f"python scripts/{script} " + " ".join(sys.argv[1:] if argv is None else argv)
    args.load = " / ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
    return args


def run_sentence(args) -> str:
    """How and where a benchmark ran: its command, the machine, the commit and the load average before the run."""
    info = machine()
    return (
        f"Command `{args.command.strip()}`; {info['cpu']}, {info['logical_cpus']} logical CPUs, torch {info['torch']} "
        f"({info['torch_threads']} threads), commit {info['git_commit']}, load average before the run {args.load}."
    )


def update_benchmarks(block: str, start: str, end: str) -> None:
    """Put ``block`` (its markers included) into BENCHMARKS.md in place of the old one, or append it."""
    path = ROOT / "BENCHMARKS.md"
    path.write_text(replace_marked(path.read_text() if path.exists() else "", block, start, end))


def publish(lines: list[str], markdown: bool, start: str, end: str) -> None:
    """Print a benchmark's block (``lines`` between the markers) and, with ``markdown``, put it into BENCHMARKS.md."""
    text = "\n".join([start, *lines, end, ""])
    print(text)
    if markdown:
        update_benchmarks(text, start, end)
