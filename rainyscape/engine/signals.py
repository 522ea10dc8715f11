"""SIGTERM (kill, a batch scheduler's stop) ends a command like Ctrl-C: training saves a
checkpoint and says interrupted; rs-bench stops its cells and starts no more."""

from __future__ import annotations


def stop_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt in this process."""
    import signal

    def stop(signum, frame):
        raise KeyboardInterrupt

    try:
        signal.signal(signal.SIGTERM, stop)
    except ValueError:  # not the main thread (tests calling main in a worker)
        pass
