"""blockloc: LiDAR-inertial localization in large prior maps, one block at a time."""

import os as _os

__version__ = "0.1.0"

# Numba's parallel kernels run on the OpenMP layer. Busy-waiting OpenMP threads make two
# threads 30x slower than one when the two cores are shared (measured, docs/bench/ndt.md), and
# naming the layer keeps numba from probing (and warning about) an old TBB. Both must be set
# before numba starts its thread pool, hence here; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")

import sys as _sys
import threading as _threading

#: CPython before 3.11.8 (and 3.12.0) keeps the ast module's recursion depth interpreter-wide: two
#: threads turning source into AST objects at once (ast.parse; numpy's .npy headers through
#: ast.literal_eval; traceback's caret lines) can fail with "SystemError: AST constructor recursion
#: depth mismatch" (python/cpython#106905, fixed in 3.11.8 and 3.12.1; CI hit it when
#: relocalization's worker threads read cached pieces). blockloc runs worker threads, so on those
#: versions every ast.parse in the process takes this lock (re-entrant: one parse may lead to another).
AST_LOCK = _threading.RLock()


def _guard_ast_parse() -> None:
    import ast
    import functools

    parse = ast.parse
    if getattr(parse, "_blockloc_guarded", False):
        return

    @functools.wraps(parse)
    def guarded(*args, **kwargs):
        with AST_LOCK:
            return parse(*args, **kwargs)

    guarded._blockloc_guarded = True
    ast.parse = guarded


if _sys.version_info[:3] < (3, 11, 8) or _sys.version_info[:3] == (3, 12, 0):
    _guard_ast_parse()
