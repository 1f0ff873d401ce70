"""One line of progress for the tools that run for a while (``record``, ``render``, the
demos), on a terminal only.

The line goes to stderr when stderr is a terminal (``isatty()``), and nowhere otherwise:
a pipe, a file, a test's captured output get none of it. It is one line, rewritten in place
(a carriage return, then the text, padded with blanks over what it replaces) at most
:data:`INTERVAL` seconds apart, cut to the terminal's width so that it never wraps (a
wrapped line could not be rewritten), and ended with a newline by :meth:`Progress.done`.
Before anything else is printed to the same terminal (a log line, a result),
:meth:`Progress.clear` blanks it; the next update draws it again.
"""
from __future__ import annotations

import shutil
import sys
import time
from typing import Optional, TextIO

__all__ = ['Progress', 'INTERVAL']

#: [s] of wall time between two updates of the line at least (four a second)
INTERVAL = 0.25


class Progress:
    """The progress line of program ``prog`` on ``stream`` (default: stderr), shown only if
    it is a terminal (``enabled`` overrides that)."""

    def __init__(self, prog: str, stream: Optional[TextIO] = None,
                 enabled: Optional[bool] = None, interval: float = INTERVAL):
        self.prog = prog
        self.stream = sys.stderr if stream is None else stream
        if enabled is None:
            try:
                enabled = self.stream.isatty()
            except (AttributeError, ValueError):       # no isatty, a closed stream
                enabled = False
        self.enabled = bool(enabled)
        self.interval = interval
        self._shown = 0               # characters of the line on screen (0: none)
        self._line = ''               # the line on screen
        self._last = -float('inf')    # when it was last drawn [monotonic s]

    def _put(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):      # the terminal went away: no more progress
            self.enabled = False

    def update(self, text: str, force: bool = False) -> None:
        """Show ``prog: text`` in place of the line, unless the last update was less than
        ``interval`` ago (``force``: anyway)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < self.interval:
            return
        width = shutil.get_terminal_size((80, 24)).columns - 1
        line = f'{self.prog}: {text}'[:max(width, 10)]
        if line == self._line and self._shown and not force:
            return                                  # the same as on screen
        self._last = now
        self._put('\r' + line + ' ' * max(0, self._shown - len(line)))
        self._shown = len(line)
        self._line = line

    def clear(self) -> None:
        """Blank the line (the cursor back at its start) so that something else can be
        printed there; the next :meth:`update` draws it again, at once."""
        if self.enabled and self._shown:
            self._put('\r' + ' ' * self._shown + '\r')
        self._shown = 0
        self._last = -float('inf')

    def done(self, text: Optional[str] = None) -> None:
        """End the line with a newline (after showing ``text``, if given), leaving it on
        the screen; nothing if no line is shown."""
        if text is not None:
            self.update(text, force=True)
        if self.enabled and self._shown:
            self._put('\n')
        self._shown = 0
        self._last = -float('inf')
