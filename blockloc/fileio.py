"""Files blockloc writes: atomically (a reader sees the old file or the new one, never half of
one), and replacing only what blockloc made.

Replace-only-what-we-made: a directory is replaced or written into only when it is empty or
carries one of blockloc's markers (:data:`OUTPUT_MARKERS`: a map store's manifest, a simulated
dataset's sidecar, a results folder's metrics); anything else is the user's and is never deleted.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator


def _umask_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success it is renamed onto ``path``.

    The temp file gets the permissions a plain ``open(path, 'w')`` would (mkstemp makes 0600).
    On any exception the temp file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, _umask_mode())
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (the format from ``path``'s suffix) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        with atomic_path(path, suffix=path.suffix) as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        plt.close(fig)
    return path


#: Files that mark a directory as blockloc's own output: a map store, a simulated dataset
#: (``blockloc sim``), a results folder (``blockloc track``), an NCLT-layout session it wrote.
OUTPUT_MARKERS = ("manifest.json", "sim.json", "metrics.json", "blockloc_session.json")


def is_blockloc_output(path: str | Path) -> bool:
    """True for a directory blockloc made (it holds one of :data:`OUTPUT_MARKERS`) or an empty one."""
    path = Path(path)
    if not path.is_dir() or path.is_symlink():
        return False
    names = {p.name for p in path.iterdir()}
    return not names or bool(names & set(OUTPUT_MARKERS))


def check_replaceable(path: str | Path, option: str = "--out") -> None:
    """Raise BlocklocError (one line naming ``path``) unless ``path`` is absent, an empty
    directory, or a directory blockloc made: the check before any work that will replace it."""
    from blockloc.errors import BlocklocError

    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        raise BlocklocError(f"{option} {path}: exists and is not a directory; blockloc replaces only "
                            "directories it made (choose another path)")
    if path.exists() and not is_blockloc_output(path):
        raise BlocklocError(f"{option} {path}: a directory blockloc did not make (no "
                            f"{' / '.join(OUTPUT_MARKERS)}); not replacing it (choose another path "
                            "or empty it)")


def replace_dir(src: str | Path, dst: str | Path) -> None:
    """Move the finished directory ``src`` to ``dst``, replacing any ``dst`` as whole as possible:
    the old one is renamed aside first and removed only after the new one is in place. A ``dst``
    that blockloc did not make (:func:`check_replaceable`) is never replaced."""
    import shutil

    src, dst = Path(src), Path(dst)
    check_replaceable(dst, "output")
    old = None
    if dst.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old-", dir=dst.parent))
        os.replace(dst, old / dst.name)
    os.replace(src, dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield an empty temp directory beside ``path``; on success it replaces ``path``
    (:func:`replace_dir`), on any exception it is removed and ``path`` is left untouched."""
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        yield tmp
        replace_dir(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def to_jsonable(x):
    """``x`` with numpy scalars/arrays as Python numbers/lists, tuples as lists, dict keys as
    strings and non-finite floats as None (JSON has no NaN)."""
    import math

    import numpy as np

    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
