"""What every ekf_vo console script shares: errors as one line, outputs checked up front.

* :func:`entry_point` wraps a ``main``: a closed stdout (``ekf-vo-params | head -1``) ends
  the program quietly, Ctrl-C ends it with status 130, neither with a traceback;
* :func:`check_writable` tells, before any long work, whether an output file can be
  written, as a :class:`UsageError` naming the option and the path.

Standard library only: :mod:`ekf_vo.config` (below the core) uses it.
"""
from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

__all__ = ['UsageError', 'HelpFormatter', 'entry_point', 'check_writable',
           'EXIT_BROKEN_PIPE', 'EXIT_INTERRUPTED']

#: exit status after stdout was closed by the reader (128 + SIGPIPE, as a shell reports it)
EXIT_BROKEN_PIPE = 141
#: exit status after Ctrl-C (128 + SIGINT)
EXIT_INTERRUPTED = 130


class UsageError(ValueError):
    """A command-line input the user can fix (printed as one line, exit status 2)."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter,
                    argparse.RawDescriptionHelpFormatter):
    """``(default: X)`` after every help text that has a default (not after flags, None
    or empty-list defaults); the description and epilog are printed as written."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        default = action.default
        if default is None or default is False or (isinstance(default, list) and not default):
            return action.help
        return super()._get_help_string(action)


def entry_point(main: Callable[..., int]) -> Callable[..., int]:
    """Decorate a console script's ``main``: BrokenPipeError on stdout and KeyboardInterrupt
    give an exit status (141, 130) instead of a traceback."""

    @functools.wraps(main)
    def wrapper(*args: Any, **kwargs: Any) -> int:
        try:
            code = main(*args, **kwargs)
            sys.stdout.flush()   # inside the try: a late EPIPE would print at exit
            return code
        except BrokenPipeError:
            # the reader is gone: point stdout at /dev/null so the flush at exit is silent
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
            return EXIT_BROKEN_PIPE
        except KeyboardInterrupt:
            print(f'{Path(sys.argv[0]).name}: interrupted', file=sys.stderr)
            return EXIT_INTERRUPTED

    return wrapper


def check_writable(path: str | Path, option: str = '') -> None:
    """Raise :class:`UsageError` unless the file ``path`` can be created (missing parent
    directories included) or overwritten. Writes nothing that stays."""
    path = Path(path)
    label = f'{option} {path}' if option else str(path)
    if path.is_dir():
        raise UsageError(f'cannot write {label}: it is a directory')
    if path.exists():
        if not os.access(path, os.W_OK):
            raise UsageError(f'cannot write {label}: permission denied')
        return
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise UsageError(f'cannot write {label}: {parent} is not a directory')
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as exc:
        raise UsageError(f'cannot write {label}: {parent} is not writable '
                         f'({exc.strerror or exc})') from None
