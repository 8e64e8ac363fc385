"""The benchmark suite (``python -m bench``); see bench/__main__.py."""

from blockloc.threads import limit_blas_threads

limit_blas_threads()  # before any benchmark imports numpy
