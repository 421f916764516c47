"""tools/split_long_strings.py (run by `make format`): long literals become adjacent pieces
that fit, and the code means the same (same AST); what cannot be split is left alone."""

# ruff: noqa: E501 - SOURCE's lines are over 100 columns on purpose

from __future__ import annotations

import ast
import importlib.util
import io
import tokenize
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("split", REPO / "tools" / "split_long_strings.py")
assert _spec and _spec.loader
split = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(split)

SOURCE = """\
def f(n, name):
    if n:
        raise ValueError(f"{name}={n!r}: not one of the values this function takes, which are {{0, 1}}")
    message = "a plain string that is long enough to go past the limit of one hundred columns, there"
    return message, "short"
"""


def test_long_literals_are_split_into_pieces_that_fit_and_mean_the_same(tmp_path):
    path = tmp_path / "m.py"
    path.write_text(SOURCE)
    assert split.split_file(path, 100) == 2
    out = path.read_text()
    assert ast.dump(ast.parse(out)) == ast.dump(ast.parse(SOURCE))
    assert max(len(line) for line in out.splitlines()) <= 100
    ns: dict = {}
    exec(compile(out, "m.py", "exec"), ns)
    exec(compile(SOURCE, "m.py", "exec"), ref := {})
    assert ns["f"](0, "x") == ref["f"](0, "x")
    try:
        ns["f"](7, "x")
    except ValueError as exc:
        assert str(exc) == "x=7: not one of the values this function takes, which are {0, 1}"
    # a piece without fields loses its f prefix (ruff F541 would flag it)
    pieces = [
        t.string
        for t in tokenize.generate_tokens(io.StringIO(out).readline)
        if t.type == tokenize.STRING
    ]
    assert len(pieces) == 5 and not pieces[1].startswith("f") and pieces[0].startswith("f")


def test_a_literal_without_spaces_or_a_short_line_is_left_alone(tmp_path):
    src = 'x = "' + "a" * 120 + '"\ny = "short"\n'
    path = tmp_path / "m.py"
    path.write_text(src)
    assert split.split_file(path, 100) == 0
    assert path.read_text() == src
