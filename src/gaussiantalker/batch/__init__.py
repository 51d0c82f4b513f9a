"""Job lists rendered in bulk (docs/batch.md): `render_jobs(jobs_path, outdir)` under `gt-render JOBS -o OUTDIR`.

A job list (batch/job_file.py) is checked whole before anything renders; a job runs as steps (batch/job_steps.py: whole,
or drives once, segments on several workers, a join) on an engine: worker processes of this machine
(batch/local.py) or actors of a Ray cluster (batch/ray_engine.py), each keeping its heads loaded (batch/worker.py);
every output goes through a partial file renamed when complete; the runner (batch/runner.py) skips what
OUTDIR/manifest.jsonl (batch/manifest.py) proves done. Imports the runtime and the sdk only, never the exporter (no
torch); Ray only for the Ray engine."""

from .engine import Engine, JobResult
from .job_file import read_jobs
from .job_steps import DEFAULT_SEGMENT_S
from .jobs import BatchError, Job
from .local import LocalEngine
from .manifest import Manifest, Record
from .runner import BatchSummary, render_jobs, run_jobs

__all__ = ["DEFAULT_SEGMENT_S", "BatchError", "BatchSummary", "Engine", "Job", "JobResult", "LocalEngine",
           "Manifest", "Record", "read_jobs", "render_jobs", "run_jobs"]
