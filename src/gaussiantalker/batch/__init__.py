"""Job lists rendered in bulk (docs/batch.md): `render_jobs(jobs_path, outdir)` under `gt-render JOBS -o OUTDIR`.

A job list (batch/job_file.py) is checked whole before anything renders; an engine (batch/engine.py; the local
one: batch/local.py, worker processes keeping their heads loaded) renders each job into a partial file renamed
when complete; the runner (batch/runner.py) skips what OUTDIR/manifest.jsonl (batch/manifest.py) proves done.
Imports the runtime and the sdk only, never the exporter (no torch)."""

from .engine import Engine, JobResult
from .job_file import read_jobs
from .jobs import BatchError, Job
from .local import LocalEngine
from .manifest import Manifest, Record
from .runner import BatchSummary, render_jobs, run_jobs

__all__ = ["BatchError", "BatchSummary", "Engine", "Job", "JobResult", "LocalEngine", "Manifest", "Record",
           "read_jobs", "render_jobs", "run_jobs"]
