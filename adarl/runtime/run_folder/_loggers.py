"""A run's scalar loggers: TorchRL's CSVLogger always, its tensorboard and wandb loggers on request, as one.

Behind :mod:`adarl.runtime.run_folder.run_dir` (``RunDir.make_logger``), which knows where each writes; this module
knows how a
scalar reaches each of them (the CSV header row, a full disk's error named, a deleted run folder never recreated).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from adarl.errors import MissingExtraError
from adarl.runtime import metrics

__all__ = ["Fanout", "csv_header", "logging_backends", "null_logger", "tensorboard_logger"]


def logging_backends(recipe) -> set[str]:
    """The recipe's logging backends that will log (wandb not when ``wandb_mode`` is disabled), each one's package
    checked first: a missing one is a :class:`~adarl.errors.MissingExtraError` naming the ``pip install``, raised
    before anything is written (``adarl run`` checks it before it makes the run folder)."""
    backends = set(recipe.logging.backends)
    if recipe.logging.wandb_mode == "disabled":
        backends.discard("wandb")
    for backend, package in (("tensorboard", "tensorboard"), ("wandb", "wandb")):
        if backend in backends and importlib.util.find_spec(package) is None:
            raise MissingExtraError(
                f"logging.backends includes {backend!r} but the {package!r} package is not installed; "
                f"install it (pip install 'adarl[{backend}]') or remove {backend!r} from logging.backends "
                f"(allowed without extras: ['csv'])"
            )
    return backends


class Fanout:
    """Send each scalar to every configured TorchRL logger (CSV always; tensorboard / wandb on request).

    ``check``: called before each scalar (the run folder is still there, :meth:`RunDir.ensure_present`), so a
    logger never recreates a deleted run folder (TorchRL's CSV logger makes the folders of a new metric's file).
    ``make``: builds the loggers at the first scalar instead (TensorBoard's writer creates its event file when made:
    each ``adarl resume`` of a complete run added one)."""

    def __init__(self, loggers=None, check=None, *, make=None):
        if (loggers is None) == (make is None):
            raise TypeError("Fanout takes loggers or make, one of them")
        self._loggers = loggers
        self._make = make
        self.check = check

    @property
    def loggers(self) -> list:
        """The loggers, built now if they were not yet."""
        if self._loggers is None:
            self._loggers = self._make()
        return self._loggers

    @property
    def started(self) -> list:
        """The loggers built so far (what there is to flush or close): none before the first scalar."""
        return self._loggers or []

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        if self.check is not None:
            self.check()
        for lg in self.loggers:
            try:
                csv_header(getattr(lg, "experiment", None), name)
                lg.log_scalar(name, float(value), step=step)
            except OSError as err:  # a full disk fails the CSV logger's flush, which names no file: name it
                if err.filename is not None:
                    raise
                exp = getattr(lg, "experiment", None)
                where = (
                    os.path.join(exp.log_dir, "scalars", name + ".csv")
                    if hasattr(exp, "files")  # CSV: the metric's own file
                    else getattr(lg, "log_dir", None)
                )
                raise OSError(err.errno, err.strerror, where) from None


def csv_header(exp, name: str) -> None:
    """Start a new metric file of TorchRL's CSV logger (``exp``: its experiment; anything else is left alone) with
    the header row ``step,value``, as pandas and spreadsheet users expect; a file that has rows is left as it is
    (run folders of earlier versions have none: readers skip a header row and take files without one)."""
    files = getattr(exp, "files", None)
    if files is None:
        return
    path = os.path.join(exp.log_dir, "scalars", name + ".csv")
    if path in files or (os.path.isfile(path) and os.path.getsize(path) > 0):
        return
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "a") as fh:
        fh.write(metrics.CSV_HEADER + "\n")


def null_logger() -> Fanout:
    """A logger that records nothing: a run loaded read-only, to evaluate it."""
    return Fanout([])


def tensorboard_logger(path: Path, *, purge_step: int | None):
    """TorchRL's TensorboardLogger, with SummaryWriter's ``purge_step`` (events at or after it are hidden)."""

    from torchrl.record import loggers as torchrl_loggers

    class _Tensorboard(torchrl_loggers.TensorboardLogger):
        def _create_experiment(self):
            from torch.utils.tensorboard import SummaryWriter  # the optional tensorboard package

            return SummaryWriter(log_dir=os.path.join(self.log_dir, self.exp_name), purge_step=purge_step)

    return _Tensorboard(exp_name="tensorboard", log_dir=str(path))
