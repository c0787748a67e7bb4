"""``report.paper_table`` of an experiment spec: a table the paper prints (its mean ± std per row and method), shown
beside ours, and the normalisation of the aggregate across its rows. Validated as the rest of
:class:`~adarl.experiments.spec.ReportSpec`: its shape here, its names against the spec's axes by
:meth:`PaperTable.check_axes`. Private module of :mod:`adarl.experiments.spec`; the report's section is
:mod:`adarl.experiments.report._paper_table`.
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from adarl.errors import did_you_mean, one_of

__all__ = ["PaperNormalisation", "PaperTable"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class PaperNormalisation(_Model):
    """Per row: normalised score = (score - random) / (reference - random), 0 = random actions, 1 = the reference."""

    random: dict[str, float] = Field(
        description="Per row (env), the return of a uniform-random policy on the nominal dynamics (measured)."
    )
    random_from: str = Field("", description="How `random` was measured (the report quotes it).")
    reference: str = Field(
        "best",
        description="The paper's column whose mean per row is 1 (e.g. 'adarl'), or 'best': the paper's best mean "
        "of the row.",
    )

    @field_validator("random", mode="before")
    @classmethod
    def _numbers(cls, v: Any) -> Any:
        if not isinstance(v, dict) or not v:
            raise ValueError(f"random must map each row (env) to its random-policy return, got {v!r}")
        for row, x in v.items():
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise ValueError(f"random.{row} must be a finite number (a return), got {x!r}")
        return {str(k): x for k, x in v.items()}


class PaperTable(_Model):
    """The paper's table: rows (values of the row axis, e.g. env) x its methods (values of the column axis, in the
    paper's order), each cell the paper's [mean, std]."""

    title: str = Field("the paper's table", description="What the paper calls it, e.g. 'Table 1'.")
    source: str = Field("", description="Where the numbers are from and what they are (the report quotes it).")
    rows: str | None = Field(
        None, description="The axis of the rows (default: the one axis other than the column axis)."
    )
    columns: list[str] = Field(
        min_length=1, description="The paper's methods as values of the column axis, in the paper's order."
    )
    labels: dict[str, str] = Field(
        default_factory=dict, description="The paper's name of a method, e.g. {adarl: AdaRL}."
    )
    extra_columns: list[str] = Field(
        default_factory=list,
        description="Values of the column axis shown after the paper's, marked as not in its table (ours only).",
    )
    values: dict[str, dict[str, tuple[float, float]]] = Field(
        description="Per row, per column of `columns`: the paper's [mean, std]; every column in every row."
    )
    normalise: PaperNormalisation | None = Field(
        None, description="How scores are normalised for the aggregate across rows (none: no aggregate)."
    )

    @field_validator("values", mode="before")
    @classmethod
    def _mean_std_pairs(cls, v: Any) -> Any:
        if not isinstance(v, dict) or not v:
            raise ValueError(f"values must map each row to {{method: [mean, std]}}, got {v!r}")
        for row, cells in v.items():
            if not isinstance(cells, dict) or not cells:
                raise ValueError(f"values.{row} must map each method to [mean, std], got {cells!r}")
            for method, cell in cells.items():
                ok = isinstance(cell, (list, tuple)) and len(cell) == 2
                ok = ok and all(
                    not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in cell
                )
                if not ok or cell[1] < 0:
                    raise ValueError(
                        f"values.{row}.{method} must be [mean, std] (two finite numbers, std >= 0), got {cell!r}"
                    )
        return {str(r): {str(m): tuple(c) for m, c in cells.items()} for r, cells in v.items()}

    @model_validator(mode="after")
    def _check(self) -> PaperTable:
        for name, names in (("columns", self.columns), ("extra_columns", self.extra_columns)):
            if len(set(names)) != len(names):
                raise ValueError(f"{name} repeats a method: {names}")
        both = sorted(set(self.columns) & set(self.extra_columns))
        if both:
            raise ValueError(f"extra_columns {both} are in the paper's columns already")
        shown = [*self.columns, *self.extra_columns]
        unknown = [k for k in self.labels if k not in shown]
        if unknown:
            raise ValueError(f"labels name {unknown}, not a column; the columns: {one_of(shown)}")
        for row, cells in self.values.items():
            extra = [m for m in cells if m not in self.columns]
            missing = [m for m in self.columns if m not in cells]
            if extra:
                hint = did_you_mean(extra[0], self.columns)
                raise ValueError(
                    f"values.{row} names {extra}, not one of the paper's columns ({one_of(self.columns)}){hint}"
                )
            if missing:
                raise ValueError(f"values.{row} has no [mean, std] for {missing} (each column, each row)")
        if self.normalise is not None:
            n = self.normalise
            if n.reference != "best" and n.reference not in self.columns:
                raise ValueError(
                    f"normalise.reference {n.reference!r} must be one of the paper's columns "
                    f"{one_of(self.columns)} or 'best'"
                )
            if set(n.random) != set(self.values):
                raise ValueError(
                    f"normalise.random must give each row of values once: rows {one_of(self.values)}, "
                    f"it gives {one_of(n.random)}"
                )
            for row in self.values:
                if self.reference_mean(row) <= n.random[row]:
                    raise ValueError(
                        f"normalise: row {row!r}'s reference mean {self.reference_mean(row):g} is not "
                        f"above its random return {n.random[row]:g}"
                    )
        return self

    def label(self, method: str) -> str:
        return self.labels.get(method, method)

    def reference_mean(self, row: str) -> float:
        """The paper's mean that normalises to 1 in ``row`` (its reference column's, or its best)."""
        ref = self.normalise.reference if self.normalise is not None else "best"
        cells = self.values[row]
        return max(m for m, _ in cells.values()) if ref == "best" else cells[ref][0]

    def normalised(self, row: str, score: float) -> float:
        """``(score - random) / (reference - random)`` in ``row`` (needs ``normalise``)."""
        rnd = self.normalise.random[row]
        return (score - rnd) / (self.reference_mean(row) - rnd)

    def row_axis(self, axes: list[str], col: str | None) -> str | None:
        """``rows``, else the one axis other than the column axis (None when there is not exactly one)."""
        if self.rows is not None:
            return self.rows
        others = [a for a in axes if a != col]
        return others[0] if len(others) == 1 else None

    def check_axes(self, axes: dict[str, list[str]], col: str | None) -> None:
        """Its names against an experiment's axes (``{axis: value names}``) and column axis: ValueError naming the
        allowed values."""
        if col is None:
            raise ValueError(f"report.paper_table needs a column axis (report.columns); axes: {list(axes)}")
        row = self.row_axis(list(axes), col)
        if row is None or row not in axes or row == col:
            others = [a for a in axes if a != col]
            raise ValueError(
                f"report.paper_table.rows must be an axis other than the column axis {col!r}: one of {others}"
                + (f" (got {self.rows!r})" if self.rows is not None else " (several: name one)")
            )
        known = axes[col]
        for name, names in (("columns", self.columns), ("extra_columns", self.extra_columns)):
            unknown = [m for m in names if m not in known]
            if unknown:
                raise ValueError(
                    f"report.paper_table.{name} name {unknown}, not values of the column axis {col!r} "
                    f"({one_of(known)}){did_you_mean(unknown[0], known)}"
                )
        unknown = [r for r in self.values if r not in axes[row]]
        if unknown:
            raise ValueError(
                f"report.paper_table.values name rows {unknown}, not values of the axis {row!r} "
                f"({one_of(axes[row])}){did_you_mean(unknown[0], axes[row])}"
            )
