"""Atomic file writes: a reader (or a resumed run) sees the old file or the complete new one.

Runs are killed and resumed (``graffmatch loops``, ``graffmatch benchmark``) and several workers
write into one folder, so every result file goes through here: a uniquely named temporary file
in the same folder, then ``os.replace``. ``fsync=True`` also survives a power cut, at a cost.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def write_bytes_atomic(path: str | Path, data: bytes, fsync: bool = False) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | Path, text: str, fsync: bool = False) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"), fsync=fsync)


def write_json_atomic(path: str | Path, doc: Any, fsync: bool = True, indent: int | None = 1) -> Path:
    return write_text_atomic(path, json.dumps(doc, indent=indent), fsync=fsync)
