"""Batch runs at scale: a local process pool or a Dask cluster, content-addressed caching.

* :class:`Job`, :func:`cache_key`, :class:`BatchSummary` (:mod:`.jobs`);
* :func:`run_jobs` (:mod:`.runner`): runs jobs, skips cached ones, survives
  failures, crashes of workers and Ctrl-C, writes a log and a summary table;
* :func:`calibrate_batch` (:mod:`.calibrate`), :func:`discover_batch`
  (:mod:`.discover`) and :func:`prepare_batch` (:mod:`.prepare`): the
  ``esmm calibrate --by``, ``esmm calibrate --discover --by`` and multi-file
  ``esmm prepare`` batches built on it (groups of files: :mod:`.groups`; the tables
  across groups: :mod:`.tables`; what an output folder holds from an earlier run:
  :mod:`.runfolder`).

See docs/guide/batch.md.
"""

from .jobs import BatchSummary, Job, JobOutcome, JobOutput, cache_key, code_version
from .runner import run_jobs

__all__ = ["BatchSummary", "Job", "JobOutcome", "JobOutput", "cache_key", "code_version", "run_jobs"]
