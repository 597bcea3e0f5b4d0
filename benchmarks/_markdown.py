"""`--markdown FILE.md`: a benchmark's results as a Markdown fragment that docs/performance.md
includes, so the documented numbers are the ones a script produced, never typed by hand.

The fragment records what a reader needs to weigh the numbers: the command, the date, the
revision, the machine (CPU, cores, memory, Python and library versions) and the load average at
the start and at the end of the run (on a shared machine the numbers move with other work). It is
written under a temporary name and renamed when the benchmark finishes, so an interrupted or
failed benchmark leaves the previous file as it was.

Use:

    ap = argparse.ArgumentParser(...)
    _markdown.add_option(ap)
    args = ap.parse_args()
    with _markdown.Report(args.markdown) as rep:   # tees stdout while the benchmark runs
        ...                                        # the benchmark, printing as before
        rep.table(["case", "µs"], rows)            # optional: results as a table
        rep.note("2.09× faster")                   # optional: a sentence under the tables

Without tables the fragment holds the benchmark's printed output verbatim; with tables, the
tables and notes only (``echo=True`` keeps the output too). Nothing here runs while a benchmark
measures: the machine is described when the fragment is written.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import importlib.metadata
import io
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

__all__ = ["add_option", "Report"]


def add_option(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--markdown", metavar="FILE.md",
                    help="also write the results, with the machine, date, command and load "
                         "average, as a Markdown fragment (docs/performance/<name>.md is what "
                         "docs/performance.md includes)")


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 2**20:.0f} GiB"
    except OSError:
        pass
    return "unknown memory"


def _versions() -> str:
    out = [f"Python {platform.python_version()}"]
    for dist in ("numpy", "numba", "fmpy", "pymavlink", "dask"):
        try:
            out.append(f"{dist} {importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            pass
    return ", ".join(out)


def _revision() -> str:
    def git(*args):
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    rev = git("rev-parse", "--short", "HEAD") or "unknown"
    # documentation does not change what a benchmark measures
    dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":!docs", ":!*.md",
                ":!mkdocs.yml")
    return rev + (" with uncommitted changes to the code" if dirty else "")


def _command() -> str:
    argv = list(sys.argv)
    try:
        argv[0] = str(Path(argv[0]).resolve().relative_to(ROOT))
    except ValueError:
        pass
    return "python " + " ".join(shlex.quote(a) for a in argv)


def _cell(x) -> str:
    return str(x).replace("|", "\\|").replace("\n", " ")


class _Tee(io.TextIOBase):
    def __init__(self, stream, sink: list):
        self.stream, self.sink = stream, sink

    def write(self, s):
        self.sink.append(s)
        return self.stream.write(s)

    def flush(self):
        self.stream.flush()


class Report:
    """Collects a benchmark's results and writes them to ``path`` (nothing when ``path`` is
    None) when the ``with`` block ends without an exception."""

    def __init__(self, path, echo: bool | None = None):
        self.path = Path(path) if path else None
        self.echo = echo
        self._out: list[str] = []
        self._tables: list[str] = []
        self._notes: list[str] = []

    def __enter__(self):
        self.started = _dt.datetime.now(_dt.timezone.utc)
        self.t0 = time.monotonic()
        self.load0 = os.getloadavg()
        if self.path is not None:
            self._stdout = sys.stdout
            sys.stdout = _Tee(sys.stdout, self._out)
        return self

    def __exit__(self, kind, value, tb):
        if self.path is not None:
            sys.stdout = self._stdout
            if kind is None:
                self.write()
        return False

    def table(self, header, rows, caption: str | None = None) -> None:
        lines = ([f"*{caption}*", ""] if caption else [])
        lines += ["| " + " | ".join(map(_cell, header)) + " |",
                  "|" + "|".join("---" for _ in header) + "|"]
        lines += ["| " + " | ".join(map(_cell, r)) + " |" for r in rows]
        self._tables.append("\n".join(lines))

    def note(self, text: str) -> None:
        self._notes.append(text)

    def fragment(self) -> str:
        wall = time.monotonic() - self.t0
        load1 = os.getloadavg()
        cores = os.cpu_count() or 1
        busy = max(self.load0[0], load1[0]) > cores
        fmt = lambda la: " / ".join(f"{x:.2f}" for x in la)  # noqa: E731
        head = [
            "<!-- generated by the benchmark script named below; do not edit by hand -->",
            "",
            f"- **Command**: `{_command()}`",
            f"- **When**: {self.started:%Y-%m-%d %H:%M} UTC, {wall:.0f} s; revision {_revision()}",
            f"- **Machine**: {_cpu()}, {cores} cores, {_memory()}; {platform.system()} "
            f"{platform.release()}; {_versions()}",
            f"- **Load average** (1 / 5 / 15 min): {fmt(self.load0)} at the start, {fmt(load1)} "
            f"at the end"
            + (f" — above the {cores} cores: other work shared the machine, so absolute times are "
               f"inflated; compare the ratios within this run" if busy else ""),
            "",
        ]
        body = list(self._tables)
        if self._notes:
            body.append("\n\n".join(self._notes))
        echo = self.echo if self.echo is not None else not self._tables
        text = "".join(self._out).rstrip()
        if echo and text:
            body.append("```text\n" + text + "\n```")
        return "\n".join(head) + "\n" + "\n\n".join(body) + "\n"

    def write(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            tmp.write_text(self.fragment(), encoding="utf-8")
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        print(f"wrote {self.path}", file=sys.stderr)
