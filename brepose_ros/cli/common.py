"""What every brepose-* command shares: clean error exits instead of tracebacks."""
from __future__ import annotations

import sys
from typing import Callable

from ..aspect_graph import AspectGraphError
from ..offline.cad import CadError
from ..camera import CameraError

#: errors that are the user's input, not a bug: print the message, exit 2
USER_ERRORS = (AspectGraphError, CadError, CameraError, FileNotFoundError, ValueError)


def run(main: Callable[[], int | None]) -> int:
    try:
        return int(main() or 0)
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
