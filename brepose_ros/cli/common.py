"""What every brepose-* command shares: one-line errors with exit status 2, never a traceback.

A user's mistake (a missing or malformed file, a bad flag value) prints ``error: <reason>``
on stderr and exits with status 2; argparse's own errors are shortened to the same one line.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Callable

from .. import __version__
from ..aspect_graph import AspectGraphError
from ..camera import CameraError
from ..offline.cad import CadError

#: errors that are the user's input, not a bug: print the message, exit 2
USER_ERRORS = (AspectGraphError, CadError, CameraError, OSError, ValueError)
#: top-level modules of the CAD stack and the mesh reader, which a robot install (no ``[compile]``
#: extra) lacks
CAD_MODULES = ("cadquery", "OCP", "trimesh")


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose errors are one line, ``PROG: error: ... (see PROG --help)``, exit 2;
    with ``--version``, and the epilog (every command's example) printed as written."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", argparse.RawDescriptionHelpFormatter)
        super().__init__(*args, **kwargs)
        self.add_argument("--version", action="version", version=f"%(prog)s (brepose_ros) {__version__}")

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind: type, test: Callable[[float], bool], what: str) -> Callable[[str], float]:
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not (math.isfinite(value) and test(value)):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text}")
        return value
    return parse


positive_float = _number(float, lambda v: v > 0, "a positive number")
non_negative_float = _number(float, lambda v: v >= 0, "a number >= 0")
positive_int = _number(int, lambda v: v > 0, "a positive integer")
non_negative_int = _number(int, lambda v: v >= 0, "an integer >= 0")
fraction = _number(float, lambda v: 0 <= v <= 1, "a number in [0, 1]")


def run(main: Callable[[], int | None]) -> int:
    try:
        return int(main() or 0)
    except USER_ERRORS as exc:
        print(f"error: {describe(exc)}", file=sys.stderr)
        return 2
    except ImportError as exc:
        if exc.name and exc.name.split(".")[0] in CAD_MODULES:
            print(f"error: this command needs the CAD stack ({exc.name} is not installed): "
                  "pip install 'brepose_ros[compile]'", file=sys.stderr)
            return 2
        raise
    except MemoryError:
        print("error: out of memory (the input is too large for this machine)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def describe(exc: Exception) -> str:
    """An exception's message on one line; OSErrors as 'reason: file'."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    return " ".join(str(exc).split())
