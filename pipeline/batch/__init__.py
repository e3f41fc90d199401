"""Batch runs at scale: a local process pool or a Dask cluster, content-addressed caching.

* :class:`Job`, :func:`cache_key`, :class:`BatchSummary` (:mod:`.jobs`);
* :func:`run_jobs` (:mod:`.runner`): runs jobs, skips cached ones, survives
  failures, crashes of workers and Ctrl-C, writes a log and a summary table;
* :func:`calibrate_batch` (:mod:`.calibrate`) and :func:`prepare_batch`
  (:mod:`.prepare`): the ``esmm calibrate --by`` and multi-file ``esmm prepare``
  batches built on it.

See docs/guide/batch.md.
"""

from .jobs import BatchSummary, Job, JobOutcome, JobOutput, cache_key, code_version
from .runner import run_jobs

__all__ = ["BatchSummary", "Job", "JobOutcome", "JobOutput", "cache_key", "code_version", "run_jobs"]
