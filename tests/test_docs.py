"""The README and docs: the commands they promise, the links between pages, the example code."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: Pages written alongside this documentation set; their links are checked once they exist.
PLANNED = {"api.md", "report.md", "diagnosis.md"}


def test_readme_keeps_the_two_quickstart_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert (
        "    python -m pip install -e . && cfm-fem sweep meshes/quadrupole.vtu --up 0:50:10 "
        "--out results/\n" in text
    )
    assert '    python -m pip install -e ".[test]" && python -m pytest -q\n' in text


def test_readme_stays_short():
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 250


def test_links_between_pages_resolve():
    missing = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            if target.startswith(("http://", "https://")):
                continue
            path = (page.parent / target).resolve()
            if not path.exists() and path.name not in PLANNED:
                missing.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not missing, missing


def test_commands_page_matches_the_parser():
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "make_commands_doc.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_readme_python_example_runs(tmp_path, monkeypatch):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102
    maps = namespace["maps"]
    assert namespace["uf"].shape == (namespace["fm"].n_nodes,)
    p50 = maps.summary["uf_units"]["p50"]
    assert 0 < p50[0] < p50[1]  # U_f grows with U_p
    assert maps.percentile(50, up_um=20) == pytest.approx(p50[1])


def test_the_version_is_stated_once_and_cited_alike():
    """pyproject.toml takes the version from the package; CITATION.cff cites the same one."""
    import cfm_fem

    assert re.search(r'^dynamic = \["version"\]$', (ROOT / "pyproject.toml").read_text(), re.M)
    cited = re.search(r'^version: "([^"]+)"$', (ROOT / "CITATION.cff").read_text(), re.M)
    assert cited and cited.group(1) == cfm_fem.__version__
