"""The launcher options of ``adarl experiment`` and ``adarl tune`` (``--launcher ray|submitit`` and their sizes),
one definition for both; light enough for the ``adarl`` parser to import at its top."""

from __future__ import annotations

import argparse

__all__ = ["add_launcher_arguments", "launcher_options"]


def add_launcher_arguments(
    p: argparse.ArgumentParser, what: str = "runs", sizes: str = "the spec's resources", urls: bool = True
) -> None:
    """``--launcher`` and its options; ``what`` names what a launcher executes, ``sizes`` the default run size,
    ``urls`` whether the output may be an fsspec URL."""
    p.add_argument(
        "--launcher",
        choices=["local", "ray", "submitit"],
        default="local",
        help=f"where {what} execute: local processes (default), Ray tasks (pip install 'adarl[ray]'), or "
        "SLURM jobs through submitit (pip install 'adarl[slurm]'); see docs/launchers.md",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="Ray cluster to join (e.g. auto, ray://head:10001; default: start a local Ray)",
    )
    p.add_argument(
        "--submitit-cluster",
        default=None,
        choices=["slurm", "local", "debug"],
        help="submitit executor (default: slurm when sbatch is found, else local)",
    )
    p.add_argument(
        "--submitit-folder",
        default=None,
        metavar="DIR",
        help="submitit's job files (default: <output>/submitit" + ("; needed with a URL output)" if urls else ")"),
    )
    p.add_argument("--cpus-per-run", type=float, default=None, help=f"CPUs per run (default: {sizes})")
    p.add_argument("--gpus-per-run", type=float, default=None, help=f"GPUs per run (default: {sizes})")
    p.add_argument(
        "--max-retries",
        type=int,
        default=3,
        help="times a run whose worker is lost is retried from its checkpoint (ray, submitit)",
    )


def launcher_options(args) -> dict:
    """The keyword arguments of :func:`~adarl.experiments.launchers.make_launcher` that the options give."""
    options = {"max_retries": args.max_retries}
    if args.launcher == "ray":
        options["address"] = args.ray_address
    if args.launcher == "submitit":
        options["cluster"] = args.submitit_cluster
        if args.submitit_folder is not None:
            options["submitit_folder"] = args.submitit_folder
    for key in ("cpus_per_run", "gpus_per_run"):
        if getattr(args, key) is not None:
            options[key] = getattr(args, key)
    return options
