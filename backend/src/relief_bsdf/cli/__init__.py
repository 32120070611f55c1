"""The `relief` command line (contract in ../shared/formats.md).

Each subcommand lives in its own module `cmd_<name>.py` with `add_parser(subparsers)`
and `run(args) -> int`.  Exit codes: 0 success, 2 bad input (one line on stderr
naming the file and the problem; traceback only with --debug), 1 internal error,
130 interrupted (Ctrl-C), 143 terminated (SIGTERM, e.g. a job scheduler's time limit).

Before a command runs, its output path (`-o/--out`) is checked (`OUTPUT_KIND`: a file or a
folder we can write; io.atomic.check_output_*), so a bad one fails before the work.
SIGTERM is handled like Ctrl-C: the work stops, finished checkpoints stay, no output is
left half-written (every output is written atomically), one line on stderr, exit 143.
`--max-pixels N` (or $RELIEF_MAX_PIXELS) overrides the height-map size limit of the readers
(io.heightmaps.DEFAULT_MAX_PIXELS).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
import traceback
from typing import Iterator

from relief_bsdf.errors import InputError, warning_line

COMMANDS = ["info", "synth", "reconstruct", "fill", "crop", "export", "plot", "simulate", "fit",
            "diagnose", "conceal", "render", "infer"]

#: what each command's -o/--out names: an output "file" or an output "dir" (folder)
OUTPUT_KIND = {"synth": "file", "reconstruct": "file", "fill": "file", "crop": "file", "export": "file",
               "plot": "file", "render": "file",
               "simulate": "dir", "fit": "dir", "diagnose": "dir", "conceal": "dir", "infer": "dir"}


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: stop like Ctrl-C (the code that cleans up after Ctrl-C runs for it too)."""


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises `Terminated` in the main thread; the old handler comes back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Terminated()
    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def add_sectors_arg(p: argparse.ArgumentParser) -> None:
    """--sectors auto|always: when the plate's loop meets a ray-traced relief by azimuth sector
    (plate.grid.TableGrid.sectors; the one help text of simulate, fit and diagnose)."""
    from relief_bsdf.plate.grid import SECTOR_CHOICES
    p.add_argument("--sectors", choices=SECTOR_CHOICES, default="auto",
                   help="inside sector tables of a ray-traced relief (the light inside the plate meets the relief "
                        "by its azimuth): auto = for an anisotropic relief or one found scattering trapped light by "
                        "azimuth; always = also for every other ray-traced relief, two sectors (a finite tile "
                        "answers by azimuth even where its statistics do not; ~1.6x the forward's time)")


def _positive_int(text: str) -> int:
    try:
        v = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}")
    return v


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """--help shows each option's default, "(default: X)", where it has one (not None / off / empty)
    and the help text does not already say it."""

    def _get_help_string(self, action):
        text = action.help or ""
        d = action.default
        if d is None or d is False or d is argparse.SUPPRESS or d == [] or "default" in text:
            return text
        return super()._get_help_string(action)


@contextlib.contextmanager
def input_warnings_as_lines(debug: bool = False) -> Iterator[None]:
    """Within the block, every warning prints as one line ``relief: warning: ...`` on stderr, once per
    message (no source line, no file name of ours); with `debug` Python's own format (file and line)."""
    import warnings

    with warnings.catch_warnings():
        default = warnings.showwarning
        said: set[str] = set()

        def show(message, category, filename, lineno, file=None, line=None):
            if debug:
                default(message, category, filename, lineno, file, line)
                return
            text = warning_line(message, category)
            if text not in said:                     # once per cause, whatever the place
                said.add(text)
                print(text, file=sys.stderr)
        warnings.showwarning = show
        yield


def check_output(args: argparse.Namespace) -> None:
    """The command's -o/--out (and --checkpoint-dir) is writable and of the right kind (file or folder);
    InputError naming it if not."""
    from relief_bsdf.io.atomic import check_output_dir, check_output_file
    ck = getattr(args, "checkpoint_dir", None)
    if ck:
        check_output_dir(ck)
    out = getattr(args, "out", None)
    kind = OUTPUT_KIND.get(args.command)
    if out is None or kind is None:
        return
    (check_output_dir if kind == "dir" else check_output_file)(out)


def build_parser() -> argparse.ArgumentParser:
    from relief_bsdf import __version__
    p = argparse.ArgumentParser(prog="relief", description="BSDF of a rough boundary from its measured micro-relief.")
    p.add_argument("--version", action="version", version=f"relief {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    p.add_argument("--max-pixels", type=_positive_int, default=None, metavar="N",
                   help="refuse height maps with more than N pixels (default 2**25, or $RELIEF_MAX_PIXELS)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"{__name__}.cmd_{name}")
        except ModuleNotFoundError as e:
            if e.name == f"{__name__}.cmd_{name}":
                continue
            raise
        sp = mod.add_parser(sub)
        sp.formatter_class = DefaultsHelpFormatter
        sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks on errors")
        sp.add_argument("--max-pixels", type=_positive_int, default=argparse.SUPPRESS, metavar="N",
                        help="refuse height maps with more than N pixels (default 2**25, or $RELIEF_MAX_PIXELS)")
        sp.set_defaults(_run=mod.run)
    return p



def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    debug = getattr(args, "debug", False)
    from relief_bsdf.io.heightmaps import pixel_limit
    from relief_bsdf.parallel import parallel_from_args
    from relief_bsdf.parallel.memory import small_pages
    small_pages()           # a command computes: no huge-page advice for its arrays (parallel.memory)

    try:
        # where the command's tasks run: its --dask/--workers/--checkpoint-dir/--retries (parallel's
        # `add_parallel_args`) over the settings in force, for the command only; a LocalCluster it
        # starts is closed when it returns, so main() leaves no state behind
        with sigterm_as_interrupt(), input_warnings_as_lines(debug), \
                pixel_limit(getattr(args, "max_pixels", None)), parallel_from_args(args):
            check_output(args)
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
    except Terminated:
        print(f"relief {args.command}: terminated (SIGTERM); finished checkpoints are kept, no output was "
              "half-written", file=sys.stderr)
        return 143
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
