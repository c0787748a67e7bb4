"""The ``ray`` launcher: one Ray task per run."""

from __future__ import annotations

import contextlib
import importlib.util
import socket

from adarl.errors import AdaRLError, AdaRLValueError, MissingExtraError
from adarl.experiments.execute import (
    WATCH_POLL_S,
    StopAsked,
    clear_stop,
    request_stop,
)
from adarl.experiments.launchers._base import Launcher, _fail, _take_result, _watch_remote
from adarl.experiments.launchers._remote_stop import _RemoteStop
from adarl.experiments.packing import execute_unit


def _ray_outcome(ray, ref, run):
    """The run of a finished Ray task, its status set; ``failed`` when the task raised (worker lost more than
    ``max_retries`` times, etc.)."""
    try:
        return _take_result(run, ray.get(ref))
    except Exception as err:  # noqa: BLE001 - any task failure is the run's failure, named
        return _fail(run, f"ray: {type(err).__name__}: {str(err).splitlines()[0]}")


def _ray_execute(run, threads, watch=None):
    return execute_unit(run, threads, watch=watch)  # a run, or a pack of runs (adarl.experiments.packing)


#: seconds the ray launcher waits for a cluster's address to answer before it gives up (one line, exit 1)
CONNECT_TIMEOUT_S = 10.0


def _host_port(address: str) -> tuple[str, int] | None:
    """``(host, port)`` of a cluster address ``host:port`` or ``ray://host:port`` (``[::1]:6379`` too); None for
    ``auto``, ``local`` or anything else Ray resolves itself."""
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _reach(address: str, timeout_s: float) -> None:
    """Refuse, in one line and within ``timeout_s`` seconds, a cluster address nothing answers at: Ray itself
    retries a dead address for minutes (``127.0.0.1:1``: no end in sight), then fails with a traceback."""
    where = _host_port(address)
    if where is None:
        return
    try:
        socket.create_connection(where, timeout=timeout_s).close()
    except OSError as err:  # refused, unreachable, unknown host, or no answer within the timeout
        why = "no answer" if isinstance(err, TimeoutError) else (err.strerror or type(err).__name__)
        raise AdaRLError(
            f"the ray launcher cannot reach the Ray cluster at {address!r}: {why} (within {timeout_s:g} s); start "
            f"it (ray start --head) or give the address it listens on (--ray-address)"
        ) from None


class RayLauncher(Launcher):
    """One Ray task per run, declaring ``cpus_per_run``/``gpus_per_run``; a task whose worker dies is retried
    (``max_retries`` times) and resumes from the run's last checkpoint.

    ``address``: an existing cluster (``"auto"``, ``"ray://head:10001"``, ...); ``None`` starts a local Ray on demand
    (``num_cpus`` CPUs, no dashboard) and stops it afterwards. Needs ``pip install 'adarl[ray]'`` (a ``ray://`` address
    also ``ray[client]``, checked here). An address nothing answers at within ``connect_timeout_s`` seconds is refused
    in one line naming it (Ray alone retried one for minutes), as is one Ray cannot join.
    """

    name = "ray"

    def __init__(
        self,
        address: str | None = None,
        *,
        cpus_per_run: float = 1,
        gpus_per_run: float = 0,
        max_retries: int = 3,
        num_cpus: int | None = None,
        poll_s: float = 5.0,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
    ) -> None:
        if cpus_per_run <= 0 or gpus_per_run < 0 or max_retries < 0:
            raise AdaRLValueError(
                f"ray launcher: cpus_per_run must be > 0, gpus_per_run and max_retries >= 0 "
                f"(got {cpus_per_run}, {gpus_per_run}, {max_retries})"
            )
        if address is not None and address.startswith("ray://") and importlib.util.find_spec("grpc") is None:
            # Ray Client's own check is a ValueError at ray.init, a traceback: refused here, before anything is written
            raise MissingExtraError(
                f"the ray launcher's address {address!r} is a Ray Client address (ray://), which needs Ray Client: "
                f"pip install 'ray[client]' (or give the cluster's host:port from a machine inside it)"
            )
        self.address, self.cpus_per_run, self.gpus_per_run = address, cpus_per_run, gpus_per_run
        self.max_retries, self.num_cpus, self.poll_s = max_retries, num_cpus, poll_s
        self.connect_timeout_s = connect_timeout_s

    @property
    def threads(self) -> int | None:
        return max(1, int(self.cpus_per_run))

    @contextlib.contextmanager
    def session(self):
        """Ray joined (``address``) or started on demand (stopped afterwards), and the run task declared."""
        try:
            import ray
        except ImportError:
            raise MissingExtraError("the ray launcher needs Ray: pip install 'adarl[ray]'") from None
        started = False
        if not ray.is_initialized():
            if self.address is None:
                ray.init(num_cpus=self.num_cpus, include_dashboard=False, log_to_driver=False, configure_logging=False)
            else:
                _reach(self.address, self.connect_timeout_s)
                try:
                    ray.init(address=self.address, log_to_driver=False, configure_logging=False)
                except Exception as err:  # noqa: BLE001 - whatever Ray says, in one line naming the address
                    why = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                    raise AdaRLError(
                        f"the ray launcher cannot join the Ray cluster at {self.address!r}: {why}"
                    ) from None
            started = True
        try:
            self._task = ray.remote(_ray_execute).options(
                num_cpus=self.cpus_per_run,
                num_gpus=self.gpus_per_run,
                max_retries=self.max_retries,
                retry_exceptions=False,
            )
            yield self
        finally:
            self._task = None
            if started:
                ray.shutdown()

    def run_watched(self, run, watch):
        import ray

        ref, asked = self._task.remote(run, self.threads, StopAsked(run.path)), [False]
        try:
            while not ray.wait([ref], timeout=WATCH_POLL_S)[0]:
                _watch_remote(run, watch, asked)
        except BaseException:  # interrupted here: the run checkpoints and stops, if Ray lets it (a while)
            request_stop(run.path)
            with contextlib.suppress(BaseException):
                ray.wait([ref], timeout=60)
            raise
        _ray_outcome(ray, ref, run)
        if asked[0]:
            clear_stop(run.path)
        return run

    def launch(self, runs, on_done, *, tick=lambda running: None) -> None:
        """One task per run. The first SIGINT or SIGTERM stops the experiment as the local launcher does (through each
        run's stop file: the running ones checkpoint and stop, ``interrupted``; a task that starts afterwards returns
        without training); a second one cancels the tasks at once (each run keeps its last checkpoint)."""
        with self.session():
            import ray

            task = self._task
            stop = _RemoteStop(runs)
            with stop:
                refs = {task.remote(r, self.threads, StopAsked(r.path)): r for r in runs}
                pending = list(refs)
                try:
                    while pending:
                        stop.poll([refs[ref] for ref in pending])
                        done, pending = ray.wait(pending, num_returns=1, timeout=min(self.poll_s, 1.0))
                        for ref in done:
                            run = stop.outcome(_ray_outcome(ray, ref, refs[ref]))
                            if run.status != "pending":  # not one asked to stop before it started
                                on_done(run)
                        tick({refs[ref].run_id for ref in pending})
                except KeyboardInterrupt:
                    if stop.interrupt.requested is None:
                        raise
                    stop.at_once = True
                    for ref in pending:
                        with contextlib.suppress(Exception):
                            ray.cancel(ref, force=True)  # its worker dies, and its training with it
                        run = stop.ended(refs[ref], "killed at once by its launcher (a second signal)")
                        if run.status != "pending":
                            on_done(run)
            stop.raise_if_asked()
