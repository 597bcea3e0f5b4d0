"""The documentation: the site builds strictly (broken links, missing pages and pages left out of
the navigation fail), the command-line reference is the parsers' own help, and the README's
relative links point at files that exist."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from cosim.cli import reference

ROOT = Path(__file__).resolve().parents[1]


def test_cli_reference_is_generated_from_the_parsers():
    page = (ROOT / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    assert page == reference.reference(), (
        "docs/reference/cli.md is out of date: python -m cosim.cli.reference > docs/reference/cli.md")


def test_cli_reference_covers_every_command():
    page = reference.reference()
    names = [n for n, _ in reference._subcommands(reference.build_parser())]
    assert names and all(f"## `se3sync {n}`" in page for n in names)


def test_docs_site_builds_strictly(tmp_path):
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q",
                        "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                       capture_output=True, text=True, env={"NO_MKDOCS_2_WARNING": "1",
                                                            "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://|#|mailto:", target):
            continue
        if not (ROOT / target.split("#")[0]).exists():
            bad.append(target)
    assert not bad, bad
