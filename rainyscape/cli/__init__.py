"""Console entry points (rs-*). Each keeps its imports light until it has work to do."""

from __future__ import annotations

import sys
from typing import Callable


def run_cli(main: Callable[[list[str]], int], argv: list[str] | None = None) -> int:
    """Run a CLI body; user errors become one clear line on stderr and a non-zero exit code."""
    from rainyscape.errors import RainyScapeError

    try:
        return main(sys.argv[1:] if argv is None else argv) or 0
    except RainyScapeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # e.g. `rs-eval --help | head`: the reader left; exit quietly
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
