"""The README's Python examples run and print what they claim."""

from __future__ import annotations

import contextlib
import io
import re

from conftest import REPO


def _examples() -> list[str]:
    text = (REPO / "README.md").read_text()
    return re.findall(r"<!-- readme-example -->\n```python\n(.*?)```", text, flags=re.S)


def test_readme_examples_run_and_print_their_comments() -> None:
    examples = _examples()
    assert examples, "README has runnable examples"
    for code in examples:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            exec(compile(code, "README.md", "exec"), {})
        expected = [m.strip() for m in re.findall(r"print\(.*#\s*(.*)$", code, flags=re.M)]
        assert out.getvalue().split("\n")[: len(expected)] == expected
