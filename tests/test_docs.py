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
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                        "-f", str(ROOT / "mkdocs.yml"), "-d", str(tmp_path / "site")],
                       capture_output=True, text=True, env={"NO_MKDOCS_2_WARNING": "1",
                                                            "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()


READMES = ("README.md", "bridge/README.md", "plant_fmu/README.md", "cosim/sweep/SWEEP.md")


def test_readme_links_resolve():
    """Markdown links and images, and HTML src attributes, of the READMEs (which GitHub shows
    outside the docs site) point at files that exist."""
    bad = []
    for name in READMES:
        path = ROOT / name
        text = path.read_text(encoding="utf-8")
        targets = re.findall(r"\]\(([^)\s]+)\)", text) + re.findall(r'src="([^"]+)"', text)
        for target in targets:
            if re.match(r"[a-z]+://|#|mailto:", target):
                continue
            if not (path.parent / target.split("#")[0]).exists():
                bad.append(f"{name}: {target}")
    assert not bad, bad


def test_readme_is_short():
    """The README introduces and points into docs/ (issue 32): at most 8 KB."""
    assert (ROOT / "README.md").stat().st_size <= 8 * 1024


def test_readme_image_is_small():
    """The picture the README shows is kept small (it is in every clone)."""
    images = re.findall(r'src="([^"]+\.png)"|!\[[^\]]*\]\(([^)\s]+\.png)\)',
                        (ROOT / "README.md").read_text(encoding="utf-8"))
    paths = [ROOT / (a or b) for a, b in images]
    assert paths and all(p.stat().st_size < 150 * 1024 for p in paths), paths


def test_performance_fragments_name_the_command_that_wrote_them():
    """docs/performance.md includes only fragments written by a benchmark script's --markdown
    option: each records its command, which names an existing script and the fragment itself."""
    page = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    included = re.findall(r'^--8<-- "([^"]+)"$', page, flags=re.M)
    assert included
    for name in included:
        text = (ROOT / "docs" / "performance" / name).read_text(encoding="utf-8")
        m = re.search(r"\*\*Command\*\*: `python (benchmarks/\S+\.py) (.*)`", text)
        assert m, f"{name}: no command recorded"
        assert (ROOT / m.group(1)).is_file(), f"{name}: {m.group(1)} does not exist"
        assert f"--markdown docs/performance/{name}" in m.group(2), f"{name}: written elsewhere"
        assert "**Load average**" in text and "**Machine**" in text, name
