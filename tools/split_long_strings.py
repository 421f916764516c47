"""Split string literals on lines over the limit into implicitly concatenated pieces, at
spaces (outside f-string fields): what `ruff format` does not do (`make format` runs both).

Each file's AST is compared before and after: adjacent literals parse to the same constant (or
the same f-string), so the code means the same; a file whose AST would change is left as is.

    python tools/split_long_strings.py [--limit 100] FILE...
"""

from __future__ import annotations

import argparse
import ast
import io
import sys
import tokenize
from pathlib import Path

PREFIX_CHARS = "rbfuRBFU"


def _split_point(body: str, is_f: bool, max_len: int) -> int | None:
    """Index just after a space in ``body[:max_len]`` outside f-string braces, or None."""
    depth = 0
    best = None
    i = 0
    while i < len(body) and i < max_len:
        c = body[i]
        if is_f and c in "{}":
            if i + 1 < len(body) and body[i + 1] == c and depth == 0:
                i += 2
                continue
            depth += 1 if c == "{" else -1
        elif c == " " and depth == 0 and i > 0 and body[i - 1] != "\\" and i + 1 < len(body):
            best = i + 1
        i += 1
    return best if best and best > 10 else None


def _has_field(body: str) -> bool:
    return "{" in body.replace("{{", "").replace("}}", "")


def _literal(prefix: str, quote: str, body: str) -> str:
    if "f" in prefix.lower() and not _has_field(body):
        prefix = prefix.replace("f", "").replace("F", "")
        body = body.replace("{{", "{").replace("}}", "}")
    return f"{prefix}{quote}{body}{quote}"


def split_file(path: Path, limit: int) -> int:
    src = path.read_text()
    lines = src.splitlines(keepends=True)
    toks = list(tokenize.generate_tokens(io.StringIO(src).readline))
    depth = 0
    edits = []  # (row, col_start, col_end, replacement) on single lines
    for t in toks:
        if t.type == tokenize.OP and t.string in "([{":
            depth += 1
        elif t.type == tokenize.OP and t.string in ")]}":
            depth -= 1
        if t.type != tokenize.STRING or t.start[0] != t.end[0]:
            continue
        row, col = t.start
        line = lines[row - 1].rstrip("\n")
        if len(line) <= limit:
            continue
        s = t.string
        prefix = s[: len(s) - len(s.lstrip(PREFIX_CHARS))]
        rest = s[len(prefix) :]
        if rest[:3] in ('"""', "'''"):
            continue
        quote = rest[0]
        body = rest[1:-1]
        is_f = "f" in prefix.lower()
        pieces = []
        trailing = len(line) - t.end[1]  # what follows the literal on its line (", )" ...)
        room = limit - col - len(prefix) - 2 - (1 if depth == 0 else 0)
        while len(body) + trailing > room:
            k = _split_point(body, is_f, room if len(body) > room else room - trailing)
            if k is None:
                break
            pieces.append(body[:k])
            body = body[k:]
            room = limit - col - len(prefix) - 2
        if not pieces:
            continue
        pieces.append(body)
        ind = " " * (col + (1 if depth == 0 else 0))
        joined = ("\n" + ind).join(_literal(prefix, quote, p) for p in pieces)
        if depth == 0:
            joined = "(" + joined + ")"
        edits.append((row, col, t.end[1], joined))
    if not edits:
        return 0
    for row, c0, c1, rep in sorted(edits, reverse=True):
        line = lines[row - 1]
        lines[row - 1] = line[:c0] + rep + line[c1:]
    new = "".join(lines)
    if ast.dump(ast.parse(src)) != ast.dump(ast.parse(new)):
        print(f"{path}: AST would change, left as is", file=sys.stderr)
        return 0
    path.write_text(new)
    return len(edits)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--limit", type=int, default=100)
    ap.add_argument("files", nargs="*", type=Path)
    a = ap.parse_args()
    n = sum(split_file(f, a.limit) for f in sorted(set(a.files)))
    print(f"{n} string literals split")


if __name__ == "__main__":
    main()
