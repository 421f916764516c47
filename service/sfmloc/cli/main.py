"""Entry point of the ``sfmloc`` console script: the one place that configures logging."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from .. import __version__
from ..errors import SfmlocError

# Subcommand modules, in the order `sfmloc --help` lists them.
COMMANDS = [
    "synth",
    "build",
    "map",
    "builder",
    "replay",
    "serve",
    "stream",
    "relocalize",
    "view",
    "maps",
    "sessions",
    "servers",
    "router",
    "auth",
    "bench",
    "bench_transport",
    "demo",
]

log = logging.getLogger("sfmloc")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sfmloc",
        description=(
            "Real-time image-based 6-DOF camera localization against Structure-from-Motion maps "
            "(Lim, Sinha, Cohen, Uyttendaele, CVPR 2012). Build a map bundle from an SfM model, "
            "serve it, and stream frames to get poses back."
        ),
        epilog="Run 'sfmloc COMMAND --help' for the options of one command.",
    )
    parser.add_argument("--version", action="version", version=f"sfmloc {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)"
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f".{name}", __package__)
        module.add_parser(sub)
    return parser


def configure_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    logging.basicConfig(
        level=level,
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
    )
    if verbose < 2:
        # Third-party chatter (faiss announces its CPU variant at INFO) stays at WARNING
        # unless debugging.
        for noisy in ("zenoh", "grpc", "faiss", "faiss.loader"):
            logging.getLogger(noisy).setLevel(logging.WARNING)


def _prestart_serve(argv: list[str]) -> bool:
    """``sfmloc [-v|-q] serve ...``: start the server's worker zygote now, before the parser
    imports every command's module (4.4 s of the server's start at load 19, nice 19; its
    zygote's imports are the longest part of a start and need nothing from the parser).
    Whether it is used is decided later (``zygote.take_prestarted``). True if started."""
    words = [a for a in argv if not a.startswith("-")]
    if not words or words[0] != "serve" or {"-h", "--help"} & set(argv):
        return False
    rest = argv[argv.index("serve") + 1 :]
    if "thread" in rest:  # --worker-kind thread: no worker processes
        return False
    from .serve import prestart_zygote

    prestart_zygote()
    return True


def main(argv: list[str] | None = None) -> int:
    prestarted = _prestart_serve(sys.argv[1:] if argv is None else list(argv))
    try:
        parser = build_parser()
        args = parser.parse_args(argv)  # inside: `sfmloc build --help | head` pipes too
        configure_logging(args.verbose, args.quiet)
        return int(args.func(args) or 0)
    except SfmlocError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        log.warning("interrupted")
        return 130
    except BrokenPipeError:
        # The reader went away (`sfmloc maps list | head`): not an error of ours. Point stdout
        # at /dev/null so the interpreter's final flush does not raise again, and exit as a
        # SIGPIPE-killed program would.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 128 + 13
    finally:
        if prestarted:  # not taken (a usage error, or a configuration that does not fork)
            from ..server.zygote import discard_prestarted

            discard_prestarted()


if __name__ == "__main__":
    sys.exit(main())
