"""Crash-safe file output: write beside the target, then rename over it."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike[str], backup: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success rename it to ``target``.

    On any exception the temporary file or directory is removed and ``target`` is left as
    it was. With ``backup`` an existing ``target`` is first copied to ``target.bak``.
    Works for files and for directories (rosbag2 recordings).
    """
    dest = Path(target)
    parent = dest.parent if str(dest.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".partial", dir=parent)) / dest.name
    try:
        yield tmp
        if tmp.is_file():
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        if backup and dest.is_file():
            bak_tmp = tmp.with_name(dest.name + ".bak")
            shutil.copy2(dest, bak_tmp)
            os.replace(bak_tmp, dest.with_name(dest.name + ".bak"))
        if dest.is_dir() and tmp.is_dir():
            shutil.rmtree(dest)
        os.replace(tmp, dest)
    finally:
        shutil.rmtree(tmp.parent, ignore_errors=True)
