"""The `relief` command line (contract in ../shared/formats.md).

Each subcommand lives in its own module `cmd_<name>.py` with `add_parser(subparsers)`
and `run(args) -> int`.  Exit codes: 0 success, 2 bad input (one line on stderr
naming the file and the problem; traceback only with --debug), 1 internal error.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from relief_bsdf.errors import InputError

COMMANDS = ["info", "synth", "reconstruct", "export", "plot", "simulate", "fit",
            "diagnose", "conceal", "render"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="relief", description="BSDF of a rough boundary from its measured micro-relief.")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"{__name__}.cmd_{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.cmd_{name}":
                continue
            raise
        sp = mod.add_parser(sub)
        sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks on errors")
        sp.set_defaults(_run=mod.run)
    return p



def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    debug = getattr(args, "debug", False)
    from relief_bsdf.parallel import parallel_from_args

    try:
        # where the command's tasks run: its --dask/--workers/--checkpoint-dir/--retries (parallel's
        # `add_parallel_args`) over the settings in force, for the command only; a LocalCluster it
        # starts is closed when it returns, so main() leaves no state behind
        with parallel_from_args(args):
            return int(args._run(args) or 0)
    except InputError as e:
        if debug:
            traceback.print_exc()
        print(f"relief {args.command}: error: {e.one_line()}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader of our stdout went away (e.g. `relief info --json | head`): not an error of ours
        import os
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except KeyboardInterrupt:
        print(f"relief {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # internal error
        if debug:
            traceback.print_exc()
        else:
            print(f"relief {args.command}: internal error: {type(e).__name__}: {e} (rerun with --debug)",
                  file=sys.stderr)
        return 1


def entry() -> None:
    sys.exit(main())
