"""Files blockloc writes: atomically (a reader sees the old file or the new one, never half of
one), and replacing only what blockloc made.

Replace-only-what-we-made: a directory is replaced or written into only when it is empty or
blockloc's own output of the right kind holding no foreign file (:mod:`blockloc.outdir`: a marker
file whose content blockloc checks); anything else is the user's and is never deleted.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from pathlib import Path
from typing import IO, Iterator

from blockloc import AST_LOCK
from blockloc.outdir import check_output_parent  # noqa: F401 - here since before outdir.py


# Reading the umask means setting it: two threads reading at once could each see the other's 0, and
# the last to restore could leave the process at 0 (every later file world-writable).
_UMASK_LOCK = threading.Lock()


def _umask() -> int:
    with _UMASK_LOCK:
        mask = os.umask(0)
        os.umask(mask)
    return mask


def _umask_mode() -> int:
    """The mode ``open(path, 'w')`` gives a new file."""
    return 0o666 & ~_umask()


def _umask_dir_mode() -> int:
    """The mode ``mkdir`` gives a new directory (``tempfile.mkdtemp`` makes 0700)."""
    return 0o777 & ~_umask()


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


#: Image formats :func:`save_figure` writes (matplotlib's, without the optional ones).
FIGURE_FORMATS = ("png", "pdf", "svg", "jpg", "jpeg", "eps", "ps", "tif", "tiff", "webp")


def check_figure_path(path: str | Path, option: str = "--out") -> Path:
    """Before any work: ``path`` must name an image file (a suffix of :data:`FIGURE_FORMATS`)
    that is not a directory, with no file where its directory should be; BlocklocError (one
    line naming ``option`` and ``path``) otherwise."""
    from blockloc.errors import BlocklocError

    path = Path(path)
    if path.is_dir():
        raise BlocklocError(f"{option} {path}: is a directory, expected an image file name (e.g. map.png)")
    if path.suffix[1:].lower() not in FIGURE_FORMATS:
        raise BlocklocError(f"{option} {path}: expected an image file name ending in "
                            f"{', '.join('.' + f for f in FIGURE_FORMATS[:3])}, ...")
    check_output_parent(path, option)
    return path


def check_output_dir(path: str | Path, option: str) -> Path:
    """Before any work: ``path`` is a directory files will be written into (never emptied):
    absent or a directory; BlocklocError naming ``option`` otherwise."""
    from blockloc.errors import BlocklocError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise BlocklocError(f"{option} {path}: exists and is not a directory (expected a directory for the files)")
    check_output_parent(path, option)
    return path


#: What every figure blockloc saves carries in its metadata (PNG text, PDF / SVG / PostScript
#: creator, a JPEG comment, a TIFF description, WebP XMP): a file at a user-chosen path is replaced
#: only when it carries it (:func:`is_blockloc_figure`).
FIGURE_MARK = "blockloc figure"


def figure_mark_kwargs(fmt: str) -> dict:
    """``savefig`` keyword arguments that put :data:`FIGURE_MARK` into a ``fmt`` file."""
    if fmt == "png":
        return {"metadata": {"Software": FIGURE_MARK}}
    if fmt in ("pdf", "svg", "eps", "ps"):
        return {"metadata": {"Creator": FIGURE_MARK}}
    if fmt in ("jpg", "jpeg"):
        return {"pil_kwargs": {"comment": FIGURE_MARK.encode()}}
    if fmt in ("tif", "tiff"):
        return {"pil_kwargs": {"description": FIGURE_MARK}}
    if fmt == "webp":
        return {"pil_kwargs": {"xmp": FIGURE_MARK.encode()}}
    return {}


def is_blockloc_figure(path: str | Path, max_bytes: int = 256 * 2**20) -> bool:
    """True when the file at ``path`` carries :data:`FIGURE_MARK` (a figure :func:`save_figure` wrote)."""
    try:
        path = Path(path)
        if path.stat().st_size > max_bytes:
            return False
        return FIGURE_MARK.encode() in path.read_bytes()
    except OSError:
        return False


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (the format from ``path``'s suffix, one of
    :data:`FIGURE_FORMATS`, marked with :data:`FIGURE_MARK`) and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        check_figure_path(path, "figure")
        fmt = path.suffix[1:].lower()
        with atomic_path(path, suffix=path.suffix) as tmp:
            fig.savefig(tmp, dpi=dpi, format=fmt, **figure_mark_kwargs(fmt))
    finally:
        plt.close(fig)
    return path


#: The kinds of blockloc's output (see :mod:`blockloc.outdir`: a marker file whose content names
#: the kind, or, for folders written before markers, the kind's own format), as the ``markers``
#: a command accepts.
OUTPUT_MARKERS = ("map store", "simulated dataset", "results folder", "session", "plot folder", "dynamicmap export")
MAP_STORE, SIM_DATASET, RESULTS = ("map store",), ("simulated dataset",), ("results folder",)


def is_blockloc_output(path: str | Path, markers: tuple[str, ...] = OUTPUT_MARKERS) -> bool:
    """True for an empty directory or one blockloc made as one of the kinds ``markers``."""
    from blockloc.outdir import is_blockloc_output as owned

    return owned(path, markers)


def check_replaceable(path: str | Path, option: str = "--out", markers: tuple[str, ...] = OUTPUT_MARKERS,
                      kind: str | None = None) -> None:
    """Raise BlocklocError (one line naming ``path``) unless ``path`` is absent, an empty
    directory, or a directory blockloc made as one of the kinds ``markers`` (``kind``: what they
    are called, e.g. "a map store") that holds no file blockloc did not write
    (:func:`blockloc.outdir.check_replaceable`): the check before any work that will replace it."""
    from blockloc.outdir import check_replaceable as check

    check(path, option, markers, kind)


def replace_dir(src: str | Path, dst: str | Path, kind: str) -> None:
    """Move the finished directory ``src`` to ``dst``, replacing any ``dst`` as whole as possible:
    the old one is renamed aside first and removed only after the new one is in place. ``src``
    gets blockloc's marker of ``kind`` (one of :data:`OUTPUT_MARKERS`, listing its files); a
    ``dst`` that is not blockloc's ``kind`` or holds a file blockloc did not write
    (:func:`check_replaceable`) is never replaced. ``dst`` gets the mode a plain ``mkdir`` would
    give it (the umask's), whatever ``src`` had."""
    import shutil

    from blockloc.outdir import write_marker

    src, dst = Path(src), Path(dst)
    write_marker(src, kind)
    check_replaceable(dst, "output", (kind,), f"a {kind}")
    os.chmod(src, _umask_dir_mode())  # a temp dir is 0700; the output gets a plain mkdir's mode
    old = None
    if dst.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old-", dir=dst.parent))
        os.replace(dst, old / dst.name)
    os.replace(src, dst)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_dir(path: str | Path, kind: str) -> Iterator[Path]:
    """Yield an empty temp directory beside ``path``; on success it replaces ``path``
    (:func:`replace_dir`, marked blockloc's ``kind``), on any exception it is removed and ``path``
    is left untouched."""
    import secrets
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        # the directory made inside the try: an exception a signal raises just after the mkdir
        # (tempfile.mkdtemp returns through more Python code) still reaches the finally
        while tmp is None:
            name = path.parent / f".{path.name}.tmp-{secrets.token_hex(4)}"
            try:
                os.mkdir(name, 0o700)
            except FileExistsError:
                continue
            tmp = name
        yield tmp
        replace_dir(tmp, path, kind)
    finally:
        if tmp is not None:
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


class RowFile:
    """A text file that grows by whole rows (``poses.tum``, ``diagnostics.csv``): each row is
    appended with one ``write`` to an unbuffered descriptor; a row that cannot be written whole
    (disk full, a read-only file system) is cut off again, so the file never ends in a torn row,
    and :class:`~blockloc.errors.OutputWriteError` names the file. A file unlinked while written
    (its folder removed) is noticed at the next row, not written into the void."""

    def __init__(self, path: str | Path) -> None:
        from blockloc.errors import OutputWriteError

        self.path = Path(path)
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o666)
        except OSError as exc:
            raise OutputWriteError.of(self.path, exc) from None
        self.size = 0

    def write(self, text: str) -> None:
        """Append ``text`` (whole rows, ending in a newline) or nothing."""
        from blockloc.errors import OutputWriteError

        data = text.encode()
        try:
            if os.fstat(self._fd).st_nlink == 0:
                raise OutputWriteError(self.path, "the file or its folder was removed during the run")
            done = 0
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except OSError as exc:
            try:
                os.ftruncate(self._fd, self.size)  # no torn row
            except OSError:
                pass
            raise OutputWriteError.of(self.path, exc) from None
        self.size += len(data)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def reserve_space(path: str | Path, nbytes: int) -> Path | None:
    """A file of ``nbytes`` allocated at ``path``, to be removed (:func:`release_space`) when the
    disk fills, so that what closes a run (its metrics) still fits; None when the file system
    cannot allocate it now (the run goes on without a reserve)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            os.posix_fallocate(fd, 0, nbytes)
        finally:
            os.close(fd)
        return path
    except (OSError, AttributeError):
        Path(path).unlink(missing_ok=True)
        return None


def release_space(path: str | Path | None) -> None:
    if path is not None:
        try:
            Path(path).unlink(missing_ok=True)
        except OSError:
            pass


# numpy parses every .npy header with ast.literal_eval, which CPython before 3.11.8 cannot run in two
# threads at once (``blockloc.AST_LOCK``; python/cpython#106905): blockloc reads its arrays through
# the two functions below, which take turns on every version.
_NPY_HEADER_LOCK = AST_LOCK


def load_array(source: str | Path | IO[bytes], mmap_mode: str | None = None):
    """The one array of a ``.npy`` file (path or binary file object); ``mmap_mode`` as np.load.
    Raises what np.load raises (OSError, ValueError, ...); an empty or cut-short file (EOFError)
    as ValueError, so that callers' ``except ValueError`` holds."""
    import numpy as np

    try:
        with _NPY_HEADER_LOCK:
            return np.load(source, mmap_mode=mmap_mode, allow_pickle=False)
    except EOFError as exc:
        raise ValueError(f"not a whole .npy file ({exc})") from None


def load_arrays(source: str | Path | IO[bytes]) -> dict:
    """Every array of a ``.npz`` file (path or binary file object), read now: name -> ndarray.
    Raises what np.load raises (OSError, ValueError, ...); a damaged archive (empty, cut short, not
    a zip: EOFError, ``zipfile.BadZipFile``) as ValueError, so that callers' ``except ValueError``
    holds."""
    import zipfile

    import numpy as np

    try:
        with _NPY_HEADER_LOCK, np.load(source, allow_pickle=False) as z:
            return {name: z[name] for name in z.files}
    except (zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"not a whole .npz archive ({exc or type(exc).__name__})") from None
