"""The README's first example runs and its assertions hold; its two commands are the documented ones."""

import pathlib
import re
import subprocess
import sys

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"


def test_readme_example_runs():
    text = README.read_text(encoding="utf-8")
    match = re.search(r"## A first example\n```python\n(.*?)```", text, re.S)
    assert match, "README has no first example"
    # A fresh interpreter: the example enables x64 itself, as a user's script would.
    result = subprocess.run(
        [sys.executable, "-c", match.group(1)], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]


def test_readme_commands_match_ci():
    text = README.read_text(encoding="utf-8")
    assert "pip install -e . && python -m jaxquat demo" in text
    test_command = 'pip install -e ".[test]" && python -m pytest'
    assert test_command in text
    ci = (README.parent / ".ci" / "run").read_text(encoding="utf-8")
    assert test_command in ci


def test_documents_the_code_cites_are_in_the_repository():
    """Docstrings, notebooks and READMEs cite only documents a user has: they cited the team's design
    notes (NUMERICS.md, PERFORMANCE.md, STYLE.md, DESIGN.md) and seed files by name, none of which
    ships (a new user's review). docs/numerics.md §n exists for every section cited."""
    root = README.parent
    files = [*root.glob("jaxquat/*.py"), *root.glob("notebooks/*.ipynb"), README]
    files.append(root / "benchmarks" / "README.md")
    numerics = (root / "docs" / "numerics.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^## (\d+)\.", numerics, flags=re.M))
    for path in files:
        text = path.read_text(encoding="utf-8")
        for name in ("NUMERICS.md", "PERFORMANCE.md", "STYLE.md", "DESIGN.md", "seeds/", ".txt`"):
            assert name not in text, (path.name, name)
        for cited in re.findall(r"docs/numerics\.md §(\d+)", text):
            assert cited in sections, (path.name, cited)
