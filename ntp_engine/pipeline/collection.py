"""A collection of scans reconstructed into one folder (``ntp batch SCAN... --out DIR``).

Every scan becomes ``DIR/<scan folder's name>``, an ordinary result with its own stage cache, so an
interrupted batch resumes scan by scan and stage by stage when run again. One scan is one unit of
work (``task_pool``): in this process one after the other, or one Ray task each (``--ray``; on a
cluster ``DIR`` must be a folder every node sees). A scan that fails is reported — one line naming
its file, as ``ntp reconstruct`` would print it — and the others go on; ``DIR/batch.json`` lists every
scan's outcome and is rewritten as each one finishes. ``DIR`` is an ntp ``collection`` folder
(``output_folder.claim``): a user's own folder is refused, never written into.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError, error_line
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress
from ..io.threads import set_threads
from ..scanner.scan_folder import load_scan
from .stages import DEFAULT_RESOLUTION, reconstruct
from .task_pool import LocalPool, TaskPool

SUMMARY = "batch.json"


@dataclass(frozen=True)
class BatchOptions:
    """What every scan of the batch is reconstructed with (``ntp reconstruct``'s options)."""

    resolution: int = DEFAULT_RESOLUTION
    model: str | None = None
    refine: bool = False
    distil: bool = False  # the scan's own network (``reconstruct(distil=True)``)
    threads: int = 0  # per scan (0: every core in this process; one CPU per Ray task)


def reconstruct_collection(
    scans: list[Path],
    out: Path,
    options: BatchOptions = BatchOptions(),
    pool: TaskPool | None = None,
    progress: Progress = QUIET,
) -> list[dict]:
    """Reconstruct every scan folder in ``scans`` into ``out/<its name>`` on ``pool`` (default:
    this process). Returns one outcome per scan, in the order given (also ``out/batch.json``):
    ``{"scan", "result", "ok", "error", "seconds", "coverage"}`` — ``error`` the one-line reason a
    scan failed. ``NtpInputError`` before any work for two scans with the same folder name or an
    ``out`` that is not a collection folder."""
    names: dict[str, Path] = {}
    for scan in scans:
        other = names.setdefault(scan.resolve().name, scan)
        if other != scan:
            raise NtpInputError(scan, f"has the same folder name as {other}: their results would share a folder")
    pool = pool or LocalPool()
    # a task pool that runs elsewhere cannot draw this process's bars
    inner = progress if isinstance(pool, LocalPool) else QUIET
    jobs = [(scan, out / scan.resolve().name) for scan in scans]
    with claim(out, "collection", inputs=tuple(scans)):
        outcomes = [_outcome(scan, result, "not run yet") for scan, result in jobs]
        bar = progress.counter("scans", len(scans), "scan")
        with pool as p:
            cpus = max(options.threads, 1)
            for i, outcome in p.map(_reconstruct_one, jobs, shared=(options, inner), cpus=cpus):
                outcomes[i] = outcome
                write_text_atomic(out / SUMMARY, json.dumps(outcomes, indent=2) + "\n")
                bar.update(1)
        bar.close()
    return outcomes


def _outcome(scan: Path, result: Path, error: str | None) -> dict:
    """A scan's entry in ``SUMMARY``, not (yet) reconstructed."""
    return {"scan": str(scan), "result": str(result), "ok": False, "error": error}


def _reconstruct_one(job: tuple[Path, Path], options: BatchOptions, progress: Progress) -> dict:
    """One scan (a Ray task's body): its outcome, never an exception — a failure is reported and
    the batch goes on."""
    scan, result = job
    t0 = time.perf_counter()
    outcome = _outcome(scan, result, None)
    try:
        set_threads(options.threads)
        rep = reconstruct(
            load_scan(scan),
            result,
            resolution=options.resolution,
            model=options.model,
            refine=options.refine,
            distil=options.distil,
            progress=progress,
        )
        outcome.update(ok=True, coverage=rep.texels.coverage if rep.texels else 0.0)
    except (NtpInputError, OSError) as err:
        outcome["error"] = error_line(err)
    except Exception as err:  # a bug on one scan must not stop the collection: say what it was
        outcome["error"] = f"{scan}: {type(err).__name__}: {' '.join(str(err).split())}"
    outcome["seconds"] = round(time.perf_counter() - t0, 3)
    return outcome
