"""Running trials on Dask (``dask.distributed``), or serially in this process.

Work is a list of *units* ``(uid, payload)`` (a trial's offsets, a sweep
point's overrides). Units are grouped into batches of ``batch``; one batch is
one Dask task, :func:`run_units`, which evaluates its units in the worker
process (the trials of a tolerance batch with their rays traced together, one
kernel launch per step for the whole batch) with an evaluator that the process builds once
per job and keeps (:data:`_EVALUATORS`): the nominal design, its first-order
model and the Dr.Jit kernels, which are compiled on the first unit and
reused by all later ones of that worker.

Where the tasks run:

* ``serial=True``: in this process, in order (no Dask);
* ``scheduler=None``: a ``dask.distributed.LocalCluster`` started here on
  127.0.0.1 (worker processes, one thread each; Dr.Jit gets
  ``cores // workers`` threads per worker), closed at the end;
* ``scheduler="tcp://HOST:PORT"``: an existing cluster's scheduler. Its
  workers need lfsim installed (same version); ``LFSIM_THREADS`` in their
  environment sets Dr.Jit's threads.

Results come back to this process as tasks finish (``as_completed``) and are
handed to ``on_records`` at once (the tolerance run appends them to its
store). A worker lost mid-run loses only its unfinished task, which the
scheduler runs again elsewhere; records are keyed by ``uid``, so the store
keeps each unit once.
"""

from __future__ import annotations

import os
from collections.abc import Callable

#: Evaluators built in this process, by job key (one per design / spec).
_EVALUATORS: dict = {}


def _evaluator(job: dict):
    ev = _EVALUATORS.get(job["key"])
    if ev is None:
        if job.get("threads"):
            from ..backend import configure

            configure(threads=int(job["threads"]))
        if job["kind"] == "tolerance":
            from .trial import TrialEvaluator

            ev = TrialEvaluator(job["raw"], job["path"], job["spec"])
        elif job["kind"] == "sweep":
            from .sweep import PointEvaluator

            ev = PointEvaluator(job["raw"], job["path"], job["reference"])
        else:  # pragma: no cover - jobs are built by this package
            raise ValueError(f"unknown job kind {job['kind']!r}")
        _EVALUATORS.clear()  # one job per worker at a time: free the previous design's state
        _EVALUATORS[job["key"]] = ev
    return ev


def run_units(job: dict, units: list) -> list[dict]:
    """Dask task: evaluate ``units`` [(uid, payload)] of ``job`` in this process; their records."""
    ev = _evaluator(job)
    if hasattr(ev, "run_many"):  # trials: every unit's rays in shared launches
        return ev.run_many(units)
    return [ev.run(uid, payload) for uid, payload in units]


def batches(units: list, batch: int) -> list[list]:
    return [units[i:i + batch] for i in range(0, len(units), max(1, int(batch)))]


#: Runs of at least this many units time two of them here first (:func:`probe`).
PROBE_AFTER = 3
#: Bytes this process holds per unit record (the record store and the summary).
BYTES_PER_RECORD = 4096.0


def probe(job: dict, units: list, on_records, what: str, limits=None, log=None) -> list:
    """Evaluate the first two units here, timed, and refuse a run whose estimate is beyond ``limits``.

    The first unit pays for the kernel compiles; the second one's time,
    times the units left, is the estimate (:mod:`lfsim.budget`; a local
    cluster's workers share this machine's cores, so together they are about
    as fast as this process), printed to ``log`` when long. Returns the units left to run. Runs of fewer than
    :data:`PROBE_AFTER` units are not probed.
    """
    import time

    from .. import budget

    if len(units) < PROBE_AFTER:
        return units
    on_records(run_units(job, units[:1]))
    t0 = time.perf_counter()
    on_records(run_units(job, units[1:2]))
    per_unit = time.perf_counter() - t0
    left = len(units) - 2
    est = budget.Estimate(f"{what}: {left:,} more at {per_unit:.2g} s each (measured on the second)",
                          per_unit * left, budget.BASE_BYTES + BYTES_PER_RECORD * len(units))
    budget.check(est, limits, log)
    return units[2:]


def run(job: dict, units: list, batch: int = 8, scheduler: str | None = None, workers: int | None = None,
        serial: bool = False, on_records: Callable[[list[dict]], None] | None = None,
        estimate: str | None = None, log=None) -> dict:
    """Evaluate every unit; records go to ``on_records`` as each batch finishes.

    ``estimate``: what the units are (e.g. ``"tolerance trials"``): the run is
    probed first (:func:`probe`) and refused beyond the command's limits
    (:func:`lfsim.budget.current`). Returns a description of where it ran:
    ``{"mode", "scheduler", "workers"}``.
    """
    on_records = on_records or (lambda recs: None)
    if estimate:
        units = probe(job, units, on_records, estimate, log=log)
    chunks = batches(units, batch)
    if serial:
        for chunk in chunks:
            on_records(run_units(job, chunk))
        return {"mode": "serial", "scheduler": None, "workers": 1}

    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if scheduler is None:
        n = int(workers or os.cpu_count() or 1)
        threads = max(1, (os.cpu_count() or 1) // n)
        job = {**job, "threads": threads}
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=":0")
        client = Client(cluster)
        where = {"mode": "local", "scheduler": cluster.scheduler_address, "workers": n}
    else:
        client = Client(scheduler, timeout="30s")
        where = {"mode": "scheduler", "scheduler": scheduler,
                 "workers": len(client.scheduler_info().get("workers", {}))}
    try:
        # The job travels with each task rather than as scattered data: a scattered
        # value has no recipe, so a worker killed while holding it could cancel every
        # task that needs it ("already forgotten"); a task of its own is retried.
        futures = [client.submit(run_units, job, chunk, pure=False, retries=2) for chunk in chunks]
        for fut in as_completed(futures):
            on_records(fut.result())
            fut.release()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return where
