"""Files the project writes: never half-written, never destroying what was there.

Every writer in `jaxshadow` and `inverse` (scenes, fitted scenes, point outputs, plots, meshes,
images) goes through `atomic_write`: the content is written to a temporary file in the target's
directory and renamed over the target only once it is complete, so a failing serialiser, a full
disk or a killed process leaves the old file (or no file) in place.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from typing import IO, Any


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside `path` for writing; on success it replaces `path` atomically.

    **Arguments:**

    - `path`: the file to write. Its directory must exist.
    - `mode`: `"w"` (text) or `"wb"` (binary).
    - `open_kwargs`: passed to `open` (e.g. `newline=""` for CSV).

    On any exception inside the block the temporary file is removed and the exception re-raised;
    `path` is then untouched. The new file gets the permissions a plain `open` would give it.

    Example:
        ```python
        import tempfile
        from pathlib import Path
        from jaxshadow.files import atomic_write

        path = Path(tempfile.mkdtemp()) / "values.csv"
        with atomic_write(path, newline="") as f:   # written to a temporary file, then renamed
            print("r,g,b", file=f)
            print("0.1,0.2,0.3", file=f)
        print(path.read_text())
        ```
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}.")
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"atomic_write: directory {directory!r} does not exist.")
    if os.path.isdir(path):
        raise IsADirectoryError(f"atomic_write: {path!r} is a directory.")
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_path(path: str | os.PathLike, writer: Any) -> None:
    """Call `writer(tmp_path)` to write a file by name (savefig, trimesh export, EXR writers),
    then rename it over `path`; on failure `path` is untouched. The temporary name keeps
    `path`'s extension, for writers that choose the format by it.

    Example:
        ```python
        import os, tempfile
        import numpy as np
        from jaxshadow.files import atomic_write_path

        path = os.path.join(tempfile.mkdtemp(), "values.npy")
        atomic_write_path(path, lambda tmp: np.save(tmp, np.ones(3)))   # tmp keeps the .npy extension
        print(np.load(path))
        ```
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"atomic_write_path: directory {directory!r} does not exist.")
    base = os.path.basename(path)
    ext = os.path.splitext(base)[1]
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=f".tmp{ext}", dir=directory)
    os.close(fd)
    try:
        writer(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
