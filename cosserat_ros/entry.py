"""The executables' entry points (``setup.py``'s console scripts): each imports its module
only when called, so that a Ctrl-C or SIGTERM while numba, numpy and rclpy load (a second
or more) ends the program with one line instead of a traceback."""
from __future__ import annotations

import importlib
import signal
import sys

__all__ = ['cloth_node', 'record', 'render', 'fold_demo', 'flag_demo', 'batch']


#: the signals received while the program's module loads
_received: list = []


def _interrupt(signum, frame):
    _received.append(signum)
    raise KeyboardInterrupt


def _interrupted(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is ``exc`` or behind it (its cause or context)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _run(program: str, module: str) -> int:
    # SIGINT and SIGTERM during the imports end the program (rclpy installs its own
    # handlers once it is up); each is noted too, in case a library's import swallows the
    # KeyboardInterrupt (a bare ``except:``) and goes on
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        main = importlib.import_module(module).main
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    except BaseException as exc:
        # a library's import may wrap the interrupt in its own error (rclpy's loader of
        # its C extension raises an AssertionError from it)
        if not (_interrupted(exc) or _received):
            raise
        main = None
    if main is None or _received:
        print(f'{program}: interrupted while starting', file=sys.stderr)
        return 130
    return main()


def cloth_node() -> int:
    return _run('cloth_node', 'cosserat_ros.ros.node')


def record() -> int:
    return _run('record', 'cosserat_ros.tools.record')


def render() -> int:
    return _run('render', 'cosserat_ros.tools.render')


def fold_demo() -> int:
    return _run('fold_demo', 'cosserat_ros.tools.fold_demo')


def flag_demo() -> int:
    return _run('flag_demo', 'cosserat_ros.tools.flag_demo')


def batch() -> int:
    return _run('batch', 'cosserat_ros.batch.cli')
