"""``--scheduler ADDRESS`` / ``--workers N`` of ``specula track`` and ``specula stereo``: sequences on Dask
(docs/dic2d.md, "Sequences on several machines (Dask)")."""
from __future__ import annotations

import contextlib

import click


def dask_options(what: str):
    """The two options, as a decorator (``what``: "frame" or "state")."""
    # only ``specula track`` has --search: the stereo help must not name it
    start = "zero (or --search)" if what == "frame" else "its own initial guess"

    def deco(f):
        f = click.option("--workers", default=None, type=click.IntRange(min=1, max=1024),
                         help=f"Measure the {what}s on a local Dask cluster of this many worker processes "
                              "(as --scheduler).")(f)
        f = click.option("--scheduler", default=None, metavar="ADDRESS",
                         help=f"Measure the {what}s on the Dask cluster of this scheduler (tcp://host:8786); this "
                              f"process reads and writes. Each {what} then starts from {start}, not from "
                              "the previous one (docs/dic2d.md, Sequences on several machines).")(f)
        return f
    return deco


def check(scheduler, workers) -> bool:
    """Whether the run is distributed (both at once: a usage error)."""
    if scheduler is not None and workers is not None:
        raise click.UsageError("give --scheduler (an existing cluster) or --workers (a local one), not both")
    return scheduler is not None or workers is not None


@contextlib.contextmanager
def dask_client(scheduler, workers):
    """None (one process), a client of the scheduler at ``scheduler``, or of a local cluster of ``workers``
    processes (closed afterwards)."""
    if scheduler is None and workers is None:
        yield None
        return
    from dic.sequence.distributed import connect, local_client

    client = connect(scheduler) if scheduler is not None else local_client(workers)
    try:
        yield client
    finally:
        cluster = getattr(client, "_specula_cluster", None)
        client.close()
        if cluster is not None:
            cluster.close()
