"""The ``sfmloc`` command line. Each subcommand lives in its own module with
``add_parser(subparsers)`` and ``run(args) -> int``; heavy imports stay inside ``run`` so
that ``--help`` is instant."""
