"""Stage cache for the pipeline: each stage's result lives in ``CACHE/<stage>/`` with the key it
was computed from and a checksum of every file it holds (``key.json``). A stage whose key is
unchanged and whose files match their checksums is loaded, not recomputed, so a re-run after an
interruption, or with only a later option changed, resumes where it stopped; a damaged entry
(truncated, edited, unreadable) is reported in one line and recomputed.

Keys are made of content, never of file times or absolute paths: input files enter by name and
SHA-256 of their bytes (``content_key``), so a copied scan (cp, git, rsync without -t) reuses its
cache and a changed photo recomputes every stage that saw it. The code is content too: each
stage's key holds ``code_version`` of the modules that compute it — their syntax trees and those of
every module of the package they import, transitively — so an upgraded ntp recomputes the stages
whose code changed (and, through the chained keys, the stages after them), and only those; an edit
to a comment or a docstring changes no tree and keeps the cache.

A stage folder is written under a temporary name (``io.atomic.temp_dir``) and renamed into place
when complete: an interrupted stage leaves nothing that looks finished (what a killed run leaves is
removed when the next run claims the folder, ``output_folder.claim``).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import os
import shutil
import stat
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .atomic import temp_dir, umask_mode
from .input_file import what_it_is
from .progress import warn

HASH_THREADS = 4  # hashlib releases the GIL on large buffers: files hash in parallel


def _plain(o):
    return o.tolist() if hasattr(o, "tolist") else str(o)  # arrays in full (str() would elide them)


def digest(obj) -> str:
    """Stable hash of a JSON-able key (numpy arrays included element by element)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_plain).encode()).hexdigest()[:20]


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (20 hex digits); ``"unreadable: <reason>"`` if it cannot be read
    or is not a regular file (a FIFO or ``/dev/zero`` is never opened), so an unreadable input
    still gets a key (and its stage reports it)."""
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            return f"unreadable: {what_it_is(st.st_mode)}"
        with open(path, "rb") as fh:
            return hashlib.file_digest(fh, "sha256").hexdigest()[:20]
    except OSError as err:
        return f"unreadable: {err.strerror}"


def content_key(paths: Sequence[Path]) -> list[list[str]]:
    """``[[name, sha256], ...]`` of files, in the order given (hashed in parallel threads)."""
    with ThreadPoolExecutor(HASH_THREADS) as pool:
        hashes = list(pool.map(file_digest, paths))
    return [[p.name, h] for p, h in zip(paths, hashes, strict=True)]


def content_digest(paths: Sequence[Path]) -> str:
    """Stable hash of files' names and bytes, in the order given."""
    return digest(content_key(paths))


def _source(module: str) -> str:
    """The source text of ``module`` (found, not imported)."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        raise ValueError(f"{module}: no Python source to version")
    return Path(spec.origin).read_text(encoding="utf-8")


def _spec(name: str) -> importlib.machinery.ModuleSpec | None:
    """``name``'s module spec, None where it is no module (e.g. a function imported by name)."""
    try:
        return importlib.util.find_spec(name)
    except (ImportError, AttributeError, ValueError):
        return None


def _is_package(module: str) -> bool:
    spec = _spec(module)
    return spec is not None and spec.submodule_search_locations is not None


@functools.cache
def _module_code(module: str) -> tuple[str, tuple[str, ...]]:
    """``module``'s syntax-tree digest (docstrings dropped) and the modules of its own top-level
    package that it imports (with each one's parent packages)."""
    tree = ast.parse(_source(module))
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    top = module.split(".")[0]
    package = module if _is_package(module) else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            if name.split(".")[0] == top and _spec(name) is not None:
                parts = name.split(".")
                found.update(".".join(parts[: k + 1]) for k in range(len(parts)))
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()[:20], tuple(sorted(found - {module}))


def code_version(modules: Sequence[str], alone: Sequence[str] = ()) -> str:
    """Digest of the code of ``modules`` (dotted names) and of every module of their package they
    import, transitively, and of ``alone``'s own code (not what it imports: a runner that imports
    every stage's modules): part of a stage's key, so a change to the code that computes a stage
    recomputes it. Syntax trees, not text: comments and docstrings do not count."""
    todo, seen = list(modules), set()
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(_module_code(m)[1])
    return digest([[m, _module_code(m)[0]] for m in sorted(seen | set(alone))])


def _files(folder: Path) -> list[str]:
    """Every file (and link) under ``folder``, as sorted POSIX paths relative to it (links not followed)."""
    found = []
    for root, dirs, names in os.walk(folder):
        rel = Path(root).relative_to(folder)
        found += [(rel / n).as_posix() for n in names]
        found += [(rel / d).as_posix() for d in dirs if Path(root, d).is_symlink()]
    return sorted(found)


class StageCache:
    """Stage results under ``folder/<stage>/`` with the key they were computed from (``get``).
    ``recomputed`` lists the stages whose entry was damaged and computed again."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.hits: list[str] = []
        self.recomputed: list[str] = []

    def get(self, stage: str, key: dict, compute: Callable[[Path], None]) -> tuple[Path, str]:
        """The folder holding ``stage``'s result for ``key`` (computed into it if missing or damaged)
        and the key's digest (to chain into later stages' keys)."""
        h = digest(key)
        final = self.folder / stage
        if self._intact(final, h):
            self.hits.append(stage)
            return final, h
        tmp = temp_dir(self.folder, stage)
        try:
            try:
                compute(tmp)
            except OSError as err:  # e.g. a write on a full disk: name the stage's place, not our temporary
                name = Path(err.filename) if isinstance(err.filename, str) else None
                if name is None or name == tmp or tmp in name.parents:
                    where = final / name.relative_to(tmp) if name is not None and name != tmp else final
                    raise OSError(err.errno, err.strerror, str(where)) from err
                raise
            files = {name: file_digest(tmp / name) for name in _files(tmp)}
            stamp = {"digest": h, "key": key, "files": files}
            (tmp / "key.json").write_text(json.dumps(stamp, indent=1, default=_plain))
            os.chmod(tmp, umask_mode(0o777))  # mkdtemp makes 0700
            if final.is_symlink():
                final.unlink()  # not ntp's: the link goes, what it points to stays
            elif final.exists():
                shutil.rmtree(final)  # the stage's previous result (the cache is ntp's own; rmtree follows no link)
            os.replace(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp)
        return final, h

    def _intact(self, final: Path, h: str) -> bool:
        """Whether ``final`` holds the result for digest ``h`` with every file as written."""
        stamp = final / "key.json"
        if final.is_symlink() or not stamp.is_file():
            return False
        try:
            meta = json.loads(stamp.read_text(encoding="utf-8"))
            if meta.get("digest") != h:
                return False  # another key: recomputed without comment
            listed = dict(meta["files"])
            # every file the stage wrote is listed: a list emptied or cut short is damage too
            unlisted = sorted(set(_files(final)) - set(listed) - {"key.json"})
            damaged = unlisted + [f for f, sha in listed.items() if file_digest(final / f) != sha]
        except (OSError, ValueError, KeyError, AttributeError, TypeError):
            damaged = ["key.json"]
        if damaged:
            where = final / damaged[0]
            warn(f"{where}: cache entry damaged (not as it was written) — recomputing the {final.name} stage")
            self.recomputed.append(final.name)
        return not damaged
