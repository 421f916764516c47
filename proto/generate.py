#!/usr/bin/env python3
"""Regenerate the committed protobuf/gRPC Python code from proto/sfmloc/v1/*.proto.

    python proto/generate.py           # write client/sfmloc_client/pb/
    python proto/generate.py --check   # exit 1 (listing files) when the committed code is stale

The generated modules live in the client package (``sfmloc_client.pb``) because both the
client and the server speak the API; imports between them are rewritten to relative ones so
they do not collide with the ``sfmloc`` package. Needs grpcio-tools (pinned in the dev extra,
so that the output is byte-for-byte reproducible).
"""

from __future__ import annotations

import argparse
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent
REPO = ROOT.parent
OUT = REPO / "client" / "sfmloc_client" / "pb"
INIT = (
    '"""Generated protobuf/gRPC code for the sfmloc v1 API. Do not edit: run\n`make proto` '
    '(proto/generate.py)."""\n'
)


def generate(dest: Path) -> list[Path]:
    from grpc_tools import protoc

    protos = sorted((ROOT / "sfmloc" / "v1").glob("*.proto"))
    if not protos:
        raise SystemExit("no .proto files under proto/sfmloc/v1")
    import grpc_tools

    well_known = Path(grpc_tools.__file__).parent / "_proto"
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "protoc",
            f"-I{ROOT}",
            f"-I{well_known}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            f"--grpc_python_out={tmp}",
            *[str(p.relative_to(ROOT)) for p in protos],
        ]
        if protoc.main(args) != 0:
            raise SystemExit("protoc failed")
        written = []
        dest.mkdir(parents=True, exist_ok=True)
        for f in sorted((Path(tmp) / "sfmloc" / "v1").iterdir()):
            text = f.read_text()
            # "from sfmloc.v1 import common_pb2 as ..." -> "from . import common_pb2 as ..."
            text = re.sub(r"^from sfmloc\.v1 import ", "from . import ", text, flags=re.M)
            (dest / f.name).write_text(text)
            written.append(dest / f.name)
        (dest / "__init__.py").write_text(INIT)
        written.append(dest / "__init__.py")
    return written


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--check", action="store_true", help="compare with the committed code instead of writing"
    )
    args = ap.parse_args()
    if not args.check:
        for p in generate(OUT):
            print(p.relative_to(REPO))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = {p.name: p.read_text() for p in generate(Path(tmp))}
    committed = {
        p.name: p.read_text() for p in OUT.glob("*") if p.is_file() and p.suffix in (".py", ".pyi")
    }
    stale = sorted(n for n in fresh.keys() | committed.keys() if fresh.get(n) != committed.get(n))
    if stale:
        print("generated code is stale (run `make proto`): " + ", ".join(stale), file=sys.stderr)
        return 1
    print("generated code is up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
