"""Speed benchmarks (``adarl bench``): the update window side by side, and whole runs against SB3 SAC.

The hub of the benchmark wing; the work is done in private modules, one job each: ``_update`` (the update-window
benchmark: AdaRL-SAC fused, without rank adaptation, stock TorchRL SAC and SB3, each measurement in its own worker
process), ``_whole_run`` (``--whole-run``: whole runs, process start to finished run folder) and ``_packed``
(``--pack``: N seeds packed in one process against the same N seeds solo, the update window or whole runs).
``python -m adarl.experiments.bench`` is the same entry point without the CLI (and the workers' command line).

The ``adarl`` parser imports this hub at its top: the update-window driver imports neither torch nor the recipe
runtime (each measurement's worker does); the whole-run and packed names load on first use (PEP 562, by name).
"""

from __future__ import annotations

from adarl.errors import AdaRLValueError
from adarl.experiments.bench import _update
from adarl.experiments.bench._update import (
    VARIANTS,
    act_latency,
    add_arguments,
    format_table,
    interleave,
    main,
    measure,
    rank_event_seconds,
    run_benchmark,
    whole_run_sb3,
)

#: the whole-run driver's names, loaded on first use (it imports the recipe runtime)
_WHOLE_RUN = (
    "WHOLE_RUN_VARIANTS",
    "DEFAULTS",
    "validate",
    "rank_interval",
    "event_threads",
    "adarl_overrides",
    "adarl_command",
    "sb3_command",
    "run_whole_runs",
    "format_whole_run_table",
    "command_line",
)
#: the packed-seeds driver's names, loaded on first use (it imports torch and the recipe runtime)
_PACKED = (
    "PACK_VARIANTS",
    "FLOOR",
    "validate_pack",
    "window_overrides",
    "pack_whole_run_overrides",
    "update_window",
    "whole_run_layouts",
    "run_pack",
    "format_pack_table",
    "pack_command_line",
)
#: the options only ``--pack`` takes
_PACK_ONLY = ("seeds", "pack_threads", "no_two_packs")

__all__ = [
    "VARIANTS",
    "interleave",
    "run_benchmark",
    "measure",
    "rank_event_seconds",
    "format_table",
    "whole_run_sb3",
    "act_latency",
    "add_arguments",
    "cli",
    "main",
    *_WHOLE_RUN,
    *_PACKED,
]


def cli(a) -> int:
    """``adarl bench``: the update window, whole runs with ``--whole-run``, packed seeds with ``--pack``."""
    if getattr(a, "pack", False):
        from adarl.experiments.bench._packed import cli as packed

        return packed(a)
    given = [f"--{n.replace('_', '-')}" for n in _PACK_ONLY if getattr(a, n, None) not in (None, False)]
    if given:
        raise AdaRLValueError(f"only --pack takes {', '.join(given)} (adarl bench --pack)")
    if getattr(a, "whole_run", False):
        from adarl.experiments.bench._whole_run import cli as whole_run

        return whole_run(a)
    return _update.cli(a)


def __getattr__(name: str):
    if name in _WHOLE_RUN:
        from adarl.experiments.bench import _whole_run as module
    elif name in _PACKED:
        from adarl.experiments.bench import _packed as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(module, name)
    globals()[name] = value  # later reads skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
