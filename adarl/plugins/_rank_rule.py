"""Rank rules by name: a recipe's ``rank.rule`` (:func:`register_rank_rule`, :func:`rank_rule`) and adarl's five
rules, declared as a plugin's would be. Private module of :mod:`adarl.plugins`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from adarl.errors import AdaRLValueError
from adarl.plugins._registry import ENTRY_POINT_GROUP, NoOptions, Registry, _path_of, _resolve, current_provider

# =====================================================================================================================
# Rank rules by name: ``rank.rule`` is looked up as ``algorithm.name`` is. A rule's keyword arguments are the
# recipe's ``rank.rule_options`` (a pydantic model per rule); adarl's five rules read their own rank-section keys
# instead (``rank.beta``, ``rank.target_rank``, ``rank.lam``: :data:`BUILTIN_RANK_RULE_KEYS`).
# =====================================================================================================================

#: adarl's own rank rules, in the order error messages list them (their recipe keys: rank.beta, target_rank, lam)
BUILTIN_RANK_RULES = ("energy", "energy_inclusive", "ratio", "fixed", "policy_fit")
#: the rank-section keys each of adarl's own rules is built from: ``{rule: {keyword argument: rank.<key>}}``
BUILTIN_RANK_RULE_KEYS: dict[str, dict[str, str]] = {
    "energy": {"beta": "beta"},
    "energy_inclusive": {"beta": "beta"},
    "ratio": {"beta": "beta"},
    "fixed": {"target_rank": "target_rank"},
    "policy_fit": {"lam": "lam"},
}
HOW_TO_REGISTER_RANK_RULE = (
    f"register one with adarl.register_rank_rule(...) in a package that declares an {ENTRY_POINT_GROUP!r} entry "
    "point, then pip install it (docs/adding-a-component.md)"
)


@dataclass(frozen=True)
class RankRuleSpec:
    """A registered ``rank.rule``.

    ``rule``: the :class:`adarl.core.rank.RankRule` subclass, or a ``"module:Class"`` path imported when a run is
    built (so this module never imports torch). ``options``: a pydantic model of ``rank.rule_options``, the rule's
    own keyword arguments (unknown keys, types and ranges are its job; give it ``extra="forbid"``); a run builds
    ``rule_class()(**arguments(rank))``. ``provider``: the distribution whose entry point registered it (None for
    adarl's own and for rules registered in-process). ``builtin``: one of adarl's five rules, built from
    ``rank.beta`` / ``rank.target_rank`` / ``rank.lam`` instead of ``rank.rule_options``."""

    name: str
    rule: Any
    options: type[BaseModel] = NoOptions
    description: str = ""
    provider: str | None = None
    builtin: bool = False

    @property
    def rule_path(self) -> str:
        return _path_of(self.rule)

    def rule_class(self) -> type:
        """The rule class (a ``"module:Class"`` path is imported now; a failure is an error naming the rule)."""
        try:
            return _resolve(self.rule)
        except (ImportError, AttributeError) as err:
            raise AdaRLValueError(
                f"rank rule {self.name!r} (from {self.provider or 'adarl'}) names {self.rule!r}, which cannot be "
                f"imported: {type(err).__name__}: {err}"
            ) from err

    def arguments(self, rank) -> dict:
        """The keyword arguments a recipe's ``rank`` section builds the rule with: adarl's own rules read their keys
        of the section (:data:`BUILTIN_RANK_RULE_KEYS`), a plugin's rule its ``rank.rule_options``."""
        keys = BUILTIN_RANK_RULE_KEYS.get(self.name) if self.builtin else None
        if keys is None:
            return dict(rank.rule_options)
        return {arg: getattr(rank, key) for arg, key in keys.items()}


_rank_rules: dict[str, RankRuleSpec] = {}
RANK_RULES: Registry[RankRuleSpec] = Registry(
    "rank.rule",
    what="rank rule",
    how=HOW_TO_REGISTER_RANK_RULE,
    order=list,
    entries=lambda: _rank_rules,
    describe=lambda old: f"rule {old.rule_path}, from {old.provider or 'adarl'}",
    same=lambda old, new: old.rule_path == new.rule_path,
    protected=BUILTIN_RANK_RULES,
)


def register_rank_rule(
    name: str,
    rule: Any = None,
    *,
    options: type[BaseModel] | None = None,
    description: str = "",
    replace: bool = False,
):
    """Register ``rank.rule: <name>``; usable as a class decorator on the rule::

        class TopKOptions(BaseModel):
            model_config = ConfigDict(extra="forbid")
            k: int = Field(8, ge=1)

        @register_rank_rule("top_k", options=TopKOptions, description="keep the k largest singular values")
        class TopK(RankRule):
            def __init__(self, k: int = 8):
                super().__init__()
                self.k = k

            def select(self, s, current_rank, min_rank, fit):
                return self.k

    A recipe then says ``rank: {rule: top_k, rule_options: {k: 4}}``. A name registered twice is an error
    (``replace=True`` to override on purpose); adarl's own five names cannot be replaced."""
    if not isinstance(name, str) or not name.isidentifier():
        raise AdaRLValueError(f"rank rule name must be an identifier (letters, digits, _), got {name!r}")
    if options is not None and not (isinstance(options, type) and issubclass(options, BaseModel)):
        raise AdaRLValueError(
            f"register_rank_rule({name!r}): options must be a pydantic BaseModel class, got {options!r}"
        )

    def _register(cls):
        if cls is None:
            raise AdaRLValueError(f"register_rank_rule({name!r}) needs a RankRule subclass or a 'module:Class' path")
        if not isinstance(cls, (str, type)):
            raise AdaRLValueError(
                f"register_rank_rule({name!r}): rule must be a RankRule subclass or a 'module:Class' path, got {cls!r}"
            )
        entry = RankRuleSpec(
            name=name,
            rule=cls,
            options=options or NoOptions,
            description=description,
            provider=current_provider(),
            builtin=name in BUILTIN_RANK_RULES,
        )
        RANK_RULES.register(name, entry, replace=replace)
        return cls

    if rule is None:
        return _register
    return _register(rule)


def rank_rule_names(*, load: bool = True) -> list[str]:
    """The registered rank rule names, adarl's own first (``load``: installed plugins first)."""
    return RANK_RULES.names(load=load)


def rank_rule(name: str) -> RankRuleSpec:
    """The :class:`RankRuleSpec` registered as ``name``; installed plugins are loaded when it is not known yet.

    >>> rank_rule("energy").rule_path, rank_rule("energy").builtin
    ('adarl.core.rank:EnergyRule', True)
    >>> rank_rule("enrgy")
    Traceback (most recent call last):
        ...
    adarl.errors.UnknownNameError: unknown rank.rule 'enrgy'; allowed: 'energy', ...; did you mean 'energy'? ...
    """
    return RANK_RULES.get(name)


# adarl's own, declared as a plugin's would be
for _name, _cls, _what in (
    ("energy", "EnergyRule", "paper Eq. 10 (rank.beta)"),
    ("energy_inclusive", "InclusiveEnergyRule", "smallest rank with energy share >= rank.beta"),
    ("ratio", "RatioRule", "paper Eq. 33, App. D.4 (rank.beta)"),
    ("fixed", "FixedRank", "truncate to rank.target_rank"),
    ("policy_fit", "PolicyFitRule", "fit/penalty trade-off of Eq. 8 (rank.lam)"),
):
    register_rank_rule(_name, f"adarl.core.rank:{_cls}", description=_what)
