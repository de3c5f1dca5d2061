"""The analysis's independent fits in the processes of a Dask cluster.

A fit is some ten thousand small torch operations per Jacobian with Python between them, so
two fits on two threads of one process wait on each other's interpreter lock, and on the
RunEngine's, the store's and the live views'; in worker processes they do not, and they
compute the same numbers to the bit.  :class:`ClusterExecutor` is the :class:`concurrent.futures.Executor` that
:func:`bluesky_offsets.model.fit.gather` hands the calls to: each call is pickled (cloudpickle:
closures included) and run on a worker of the twin's cluster (a LocalCluster of one-thread
processes by default, or any scheduler address), which computes the same numbers as a thread
of this process would (one torch thread, one BLAS thread, the same library).

A progress callback cannot cross to another process as it is (the plans' is a queue's
``put``); wrapped in :class:`Progress` it crosses as a publisher on a Dask event topic, and the
executor forwards the topic's events to the callback here.
"""

from __future__ import annotations

import contextlib
import contextvars
import uuid
from collections.abc import Callable
from concurrent.futures import Executor, Future

#: the executor pickling a call in this context (topics for the Progress callbacks it meets)
_SENDING: contextvars.ContextVar[ClusterExecutor | None] = contextvars.ContextVar("_SENDING", default=None)


@contextlib.contextmanager
def one_thread():
    """One torch thread and one BLAS thread for the fits run here.

    Every sum is then in the same order whatever the machine's cores (here and on a worker alike).
    """
    import torch
    from threadpoolctl import threadpool_limits
    torch.set_num_threads(1)
    with threadpool_limits(1, user_api="blas"):
        yield


class Progress:
    """A progress callback that can be sent to a worker process.

    Here it calls ``callback(record)``; pickled by a :class:`ClusterExecutor` it becomes a
    :class:`_Published` on an event topic whose records the executor hands to ``callback``.
    """

    def __init__(self, callback: Callable[[dict], None]):
        self.callback = callback

    def __call__(self, record: dict) -> None:
        """Hand ``record`` to the callback."""
        self.callback(record)

    def __reduce__(self):
        sender = _SENDING.get()
        if sender is None:
            raise TypeError("a Progress crosses to another process only through a ClusterExecutor")
        return _Published, (sender.topic_for(self),)


class _Published:
    """A worker's side of a :class:`Progress`: each record an event on ``topic``."""

    def __init__(self, topic: str):
        self.topic = topic

    def __call__(self, record: dict) -> None:
        from distributed import get_worker
        # the records' numbers as plain Python numbers (the event travels as msgpack)
        plain = {k: (v.item() if hasattr(v, "item") else v) for k, v in record.items()}
        get_worker().log_event(self.topic, plain)


class ClusterExecutor(Executor):
    """Calls on the workers of a Dask ``client``'s cluster, each pickled with cloudpickle.

    The :class:`Progress` callbacks in them are forwarded here as the workers report.  A call that
    holds this executor gets none on the worker (its own calls run there one after the other).
    """

    def __init__(self, client):
        self.client = client
        self._remote = client.get_executor(pure=False)  # Dask's own concurrent.futures face
        self._topics: dict[int, tuple[str, Progress]] = {}

    def topic_for(self, progress: Progress) -> str:
        """The event topic that carries ``progress``'s records here (subscribed at the first call)."""
        key = id(progress)
        if key not in self._topics:
            topic = f"bluesky-offsets-progress-{uuid.uuid4().hex}"
            self.client.subscribe_topic(topic, lambda event, cb=progress.callback: cb(event[1]))
            self._topics[key] = (topic, progress)  # held: its id stays its own
        return self._topics[key][0]

    def submit(self, fn, /, *args, **kwargs) -> Future:
        """Run ``fn(*args, **kwargs)`` on a worker of the cluster, pickled with cloudpickle.

        Returns the future of its result.
        """
        import cloudpickle
        token = _SENDING.set(self)
        try:
            blob = cloudpickle.dumps((fn, args, kwargs))
        finally:
            _SENDING.reset(token)
        return self._remote.submit(_unpickle_and_call, blob)  # a call's own error raised where it is read

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop forwarding progress: unsubscribe the topics (the client and its cluster stay up)."""
        for topic, _ in self._topics.values():
            try:
                self.client.unsubscribe_topic(topic)
            except Exception:  # the client already closed: nothing left to forward
                pass
        self._topics.clear()

    def __reduce__(self):
        # sent inside a call: that call's own calls run on its worker one after the other
        return type(None), ()


def _unpickle_and_call(blob: bytes):
    """A call on a worker, on one thread as on this side (whatever the worker's own settings)."""
    import cloudpickle
    with one_thread():
        fn, args, kwargs = cloudpickle.loads(blob)
        return fn(*args, **kwargs)


@contextlib.contextmanager
def analysis_executor(threads: int, twin=None):
    """The executor an analysis's independent fits run on (None for one thread).

    Each fit runs on one torch thread and one BLAS thread: on the workers of ``twin``'s Dask cluster
    (:class:`~bluesky_offsets.model.cluster.ClusterExecutor`; the cluster starts here if it has
    not) unless the twin traces in this process (``scheduler="inline"``), else on ``threads``
    threads of this process.  Why not torch's or BLAS's own threads: the fits'
    arrays (10^4-10^5 rays, Jacobians of 10^4 rows) are too small to share, while whole fits
    run side by side with little in common (docs/benchmarks.md, "Torch engine").  One BLAS thread also keeps the
    arithmetic (the order of a matrix product's sums) the same on any number of cores.  Why
    processes where there is a cluster: see the module text.
    """
    with one_thread():
        if threads <= 1:
            yield None
            return
        if twin is not None and twin.scheduler != "inline":
            ex = ClusterExecutor(twin.client)
            try:
                yield ex
            finally:
                ex.shutdown()
            return
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(threads, thread_name_prefix="fit") as pool:
            yield pool
