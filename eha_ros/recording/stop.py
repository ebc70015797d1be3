"""Stopping the command-line tools cleanly: SIGINT and SIGTERM set a flag the tool's loop
checks, so a file being written is finished and closed instead of cut by an exception."""

from __future__ import annotations

import signal

__all__ = ['StopRequest']


class StopRequest:
    """Catch SIGINT and SIGTERM from now on; ``requested`` turns true when one arrives and
    :meth:`restore` puts the previous handlers back."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested = False
        self._previous = {s: signal.signal(s, self._request) for s in self.SIGNALS}

    def _request(self, signum, frame):
        self.requested = True

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
