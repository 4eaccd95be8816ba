"""The `quatrack` command line: a thin layer over the packages' public functions.

Subcommands register themselves in ``COMMANDS``: each is ``(add_arguments, run)``, where ``run``
takes the parsed arguments and returns an exit status. User errors are raised as
:class:`UserError` (or ``ValueError``/``OSError`` from the layers below) and become a one-line
message on stderr with exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable


class UserError(Exception):
    """Bad input from the user: reported as one line, exit status 2."""


def _add_bench(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    ude = sub.add_parser(
        "ude-cube",
        help="reproduce Ude (1999), Section 5: the cube tracked by the quaternion filter",
        description="Ude (1999), Section 5, over many seeds, with Cramér–Rao bounds and timings.",
    )
    ude.add_argument("--seeds", type=int, default=20, help="Monte-Carlo runs (default 20)")
    ude.add_argument("--first-seed", type=int, default=0, help="first random seed (default 0)")
    ude.add_argument("--table-frame", type=int, default=90, help="frame whose iterations are printed as Table 1 (default 90, t = 3 s)")
    ude.add_argument("--json", action="store_true", help="print one JSON object instead of the report")


def _run_bench(args: argparse.Namespace) -> int:
    if args.benchmark == "ude-cube":
        from quatrack.bench import ude_cube

        if args.seeds < 2:
            raise UserError("--seeds must be at least 2")
        if not 1 <= args.table_frame <= 180:
            raise UserError("--table-frame must be between 1 and 180")
        return ude_cube.main(args.seeds, args.first_seed, args.table_frame, args.json)
    raise UserError(f"unknown benchmark {args.benchmark!r}")


COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "bench": ("run a benchmark and print its figures", _add_bench, _run_bench),
}


def build_parser() -> argparse.ArgumentParser:
    from quatrack import __version__

    parser = argparse.ArgumentParser(
        prog="quatrack",
        description="Find a known textured object, estimate its 6-DoF pose, and track it.",
    )
    parser.add_argument("--version", action="version", version=f"quatrack {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, add_arguments, _) in COMMANDS.items():
        add_arguments(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    run = COMMANDS[args.command][2]
    try:
        return run(args)
    except KeyboardInterrupt:
        print("quatrack: interrupted", file=sys.stderr)
        return 130
    except (UserError, ValueError, OSError) as exc:
        print(f"quatrack {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
