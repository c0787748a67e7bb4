"""Launchers: where an experiment's runs execute. ``local`` (a process pool on this machine, the default),
``ray`` (one Ray task per run, on an existing cluster or a Ray started on demand) and ``submitit`` (one SLURM job
per run, or submitit's local executor).

Every launcher runs the same thing: :func:`adarl.experiments.execute.execute_run`, which starts ``adarl run`` (or
``adarl resume`` when the run folder has a checkpoint) in a child process that dies with its launcher process. So a
worker that is lost mid-run is retried from the run's last checkpoint (Ray: ``max_retries``; submitit: resubmitted by
the driver, and requeued from the checkpoint on preemption/timeout), and a finished run is never started again. Runs
write into the experiment's output: a filesystem path that every worker sees (NFS, Lustre, ...), or an fsspec URL
(``s3://...``) that each run uploads to from a local scratch folder (:mod:`adarl.runtime.run_folder.results`). The
launchers do not
stage code or install packages on workers: each worker needs ``adarl`` installed (and the URL's fsspec backend, e.g.
``s3fs``, with its credentials), or the output folder mounted at the same path.

A hub: each launcher lives in a private module (``_local``, ``_ray``, ``_submitit``), beside the contract they share
(``_base``) and the first-signal stop of the two whose runs train elsewhere (``_remote_stop``).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from adarl.errors import AdaRLValueError, MissingExtraError
from adarl.experiments.launchers._base import ExperimentInterrupted, Launcher
from adarl.experiments.launchers._local import LocalLauncher
from adarl.experiments.launchers._ray import RayLauncher
from adarl.experiments.launchers._submitit import SubmititLauncher
from adarl.runtime.run_folder.results import is_url

__all__ = [
    "Launcher",
    "LocalLauncher",
    "RayLauncher",
    "SubmititLauncher",
    "make_launcher",
    "LAUNCHERS",
    "ExperimentInterrupted",
]

LAUNCHERS = ("local", "ray", "submitit")


def make_launcher(
    name: str,
    *,
    workers: int = 1,
    output: str | os.PathLike = ".",
    address: str | None = None,
    cpus_per_run: float | None = None,
    gpus_per_run: float | None = None,
    max_retries: int = 3,
    resources=None,
    cluster: str | None = None,
    submitit_folder: str | os.PathLike | None = None,
) -> Launcher:
    """A launcher by name (``local``, ``ray``, ``submitit``), sized from the spec's ``resources`` unless given.

    ``submitit_folder``: where submitit keeps its job files (default ``<output>/submitit``; required when the output
    is a URL, since SLURM jobs read them from a shared filesystem)."""
    if name not in LAUNCHERS:
        raise AdaRLValueError(f"unknown launcher {name!r}; choose one of {', '.join(LAUNCHERS)}")
    cpus = cpus_per_run if cpus_per_run is not None else (resources.cpus_per_run if resources else 1)
    gpus = gpus_per_run if gpus_per_run is not None else (resources.gpus_per_run if resources else 0)
    if name == "local":
        return LocalLauncher(workers)
    package, extra = {"ray": ("ray", "ray"), "submitit": ("submitit", "slurm")}[name]
    if importlib.util.find_spec(package) is None:  # before the experiment writes anything
        raise MissingExtraError(f"the {name} launcher needs {package}: pip install 'adarl[{extra}]'")
    if name == "ray":
        return RayLauncher(address, cpus_per_run=cpus, gpus_per_run=gpus, max_retries=max_retries)
    if submitit_folder is None and is_url(output):
        raise AdaRLValueError(
            f"the submitit launcher keeps its job files in a folder every job can read; with an "
            f"fsspec URL as output ({output}) give one: --submitit-folder /shared/path"
        )
    folder = Path(submitit_folder) if submitit_folder is not None else Path(output) / "submitit"
    return SubmititLauncher(
        folder,
        cluster=cluster,
        cpus_per_run=int(cpus),
        gpus_per_run=int(gpus),
        timeout_min=resources.timeout_min if resources else 24 * 60,
        slurm_partition=resources.slurm_partition if resources else None,
        slurm_additional_parameters=resources.slurm_additional_parameters if resources else None,
        max_retries=max_retries,
    )
