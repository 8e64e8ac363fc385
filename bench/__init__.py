"""The benchmark suite (``python -m bench``); see bench/__main__.py."""

import os
import sys

from blockloc.threads import limit_blas_threads

limit_blas_threads()  # before any benchmark imports numpy

#: Set (to anything) to see the traceback of a user error in a benchmark.
DEBUG_ENV = "BLOCKLOC_DEBUG"


def _one_line_user_errors(exc_type, exc, tb, _default=sys.excepthook):
    """A BlocklocError that reaches the top of ``python -m bench.<part>`` (an unknown ``--set`` key,
    a missing map or data file) is printed as one line, as the CLI prints it, and the process exits
    1; anything else, or any error with ``BLOCKLOC_DEBUG`` set, keeps its traceback."""
    from blockloc.errors import BlocklocError

    if issubclass(exc_type, BlocklocError) and not os.environ.get(DEBUG_ENV):
        print(f"error: {exc} (set {DEBUG_ENV}=1 for a traceback)", file=sys.stderr)
        return
    _default(exc_type, exc, tb)


sys.excepthook = _one_line_user_errors
