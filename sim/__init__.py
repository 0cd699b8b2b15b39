"""fall-guard's simulator: PyBullet episodes of a walking Poppy Humanoid, written as MCAP.

See sim/README.md. pybullet prints its build time on stdout when imported; it is
imported here once with stdout silenced so that the CLI's stdout stays JSON.
"""

import os as _os
import sys as _sys


def _import_pybullet_quietly() -> None:
    try:
        _sys.stdout.flush()
        saved = _os.dup(1)
    except (OSError, ValueError, AttributeError):
        import pybullet  # noqa: F401
        return
    devnull = _os.open(_os.devnull, _os.O_WRONLY)
    try:
        _os.dup2(devnull, 1)
        import pybullet  # noqa: F401
        try:  # the message sits in C's stdio buffer: flush it into /dev/null
            import ctypes
            ctypes.CDLL(None).fflush(None)
        except (OSError, AttributeError):
            pass
    finally:
        _os.dup2(saved, 1)
        _os.close(saved)
        _os.close(devnull)


_import_pybullet_quietly()
