"""The command-line reference of the docs (docs/reference/cli.md), generated from the argparse
parsers themselves, so that `--help` and the documentation cannot diverge.

    python -m cosim.cli.reference > docs/reference/cli.md       # regenerate
    python -m cosim.cli.reference --check docs/reference/cli.md  # exit 1 when it is out of date

The help text is formatted at a fixed width (argparse reads $COLUMNS), so the page does not depend
on the terminal that generated it. `tests/test_docs.py` runs the check.
"""
from __future__ import annotations

import argparse
import os
import sys

from . import build_parser

__all__ = ["reference", "main"]

WIDTH = 100

_HEAD = """# Command-line reference

Generated from the parsers by `python -m cosim.cli.reference` (do not edit by hand; a test
compares this page with the parsers). Every command exits 0 on success, 2 on bad input (one line
on stderr naming the option or scenario key), 130 on Ctrl-C and 143 on SIGTERM (outputs finished,
summaries with `"interrupted": true`); commands that add their own statuses say so below.

"""


def _subcommands(parser: argparse.ArgumentParser):
    for action in parser._actions:  # argparse keeps its sub-parsers only here
        if isinstance(action, argparse._SubParsersAction):
            return sorted(action.choices.items())
    return []


def reference() -> str:
    """The Markdown page: the top-level help, then one section per sub-command."""
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(WIDTH)
    try:
        parser = build_parser()
        out = [_HEAD, "## `se3sync`\n\n```text\n", parser.format_help().rstrip(), "\n```\n"]
        todo = [(f"se3sync {name}", sub) for name, sub in _subcommands(parser)]
        while todo:   # depth first, so `fmu build` follows `fmu`
            name, sub = todo.pop(0)
            out += [f"\n## `{name}`\n\n```text\n", sub.format_help().rstrip(), "\n```\n"]
            todo[:0] = [(f"{name} {n}", s) for n, s in _subcommands(sub)]
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old
    return "".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cosim.cli.reference",
                                 description="Print the CLI reference page, or check a copy.")
    ap.add_argument("--check", metavar="FILE",
                    help="compare FILE with the generated page; exit 1 when they differ")
    args = ap.parse_args(argv)
    page = reference()
    if args.check is None:
        sys.stdout.write(page)
        return 0
    try:
        with open(args.check, encoding="utf-8") as f:
            same = f.read() == page
    except OSError as exc:
        print(f"{ap.prog}: error: --check: {exc.strerror}: {args.check}", file=sys.stderr)
        return 2
    if not same:
        print(f"{args.check} is out of date: regenerate it with "
              f"`python -m cosim.cli.reference > {args.check}`", file=sys.stderr)
    return 0 if same else 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
