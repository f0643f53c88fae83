"""Stage cache for the pipeline: each stage's result lives in ``CACHE/<stage>/`` with the key it
was computed from (``key.json``). A stage whose key is unchanged is loaded, not recomputed, so a
re-run after an interruption, or with only a later option changed, resumes where it stopped.

A stage folder is written under a temporary name and renamed into place when complete: an
interrupted stage leaves nothing that looks finished.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path


def _plain(o):
    return o.tolist() if hasattr(o, "tolist") else str(o)  # arrays in full (str() would elide them)


def digest(obj) -> str:
    """Stable hash of a JSON-able key (numpy arrays included element by element)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_plain).encode()).hexdigest()[:20]


def content_digest(paths: list[Path]) -> str:
    """Stable hash of files' names and bytes, in the order given."""
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:20]


def file_key(path: Path) -> dict:
    """What identifies an input file in a stage key: name, size and modification time."""
    st = path.stat()
    return {"name": path.name, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


class StageCache:
    """Stage results under ``folder/<stage>/`` with the key they were computed from (``get``)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.hits: list[str] = []

    def get(self, stage: str, key: dict, compute: Callable[[Path], None]) -> tuple[Path, str]:
        """The folder holding ``stage``'s result for ``key`` (computed into it if missing) and the
        key's digest (to chain into later stages' keys)."""
        h = digest(key)
        final = self.folder / stage
        stamp = final / "key.json"
        if stamp.is_file() and json.loads(stamp.read_text()).get("digest") == h:
            self.hits.append(stage)
            return final, h
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{stage}.", dir=self.folder))
        try:
            compute(tmp)
            (tmp / "key.json").write_text(json.dumps({"digest": h, "key": key}, indent=1, default=_plain))
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
        return final, h
