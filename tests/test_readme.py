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
